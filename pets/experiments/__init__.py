"""A/B experiments over envs, models and seeds: the ``compare`` command (:mod:`pets.experiments.cli`) and its parts."""
