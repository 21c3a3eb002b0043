"""PETS: the model table, training, trajectory sampling, planners, the MBRL loop, the offline tools and experiments."""
