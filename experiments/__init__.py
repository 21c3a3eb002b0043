"""A/B experiments over envs, models and seeds: the ``compare`` command (:mod:`experiments.cli`) and its parts."""
