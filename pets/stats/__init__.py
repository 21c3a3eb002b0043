"""Statistics the library itself reports (the open-loop tool's per-episode means and bands); the A/B statistics of
the experiments (:mod:`pets.experiments.statistics`) build on them."""
