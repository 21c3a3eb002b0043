"""From the env to transitions: running episodes with a policy (:mod:`~pets.data.rollout`), collecting data sets
(:mod:`~pets.data.collect`), their ``.npz`` format (:mod:`~pets.data.datasets`), the training protocols
(:mod:`~pets.data.protocols`), the replay buffer (:mod:`~pets.data.buffer`) and Stable-Baselines3 agents
(:mod:`~pets.data.sb3`)."""
