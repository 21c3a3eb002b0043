"""The dynamics models every part of the project builds on: heads, member networks, the model that joins them.

Depends only on ``envs`` (observation layouts) and torch; ``gem_head`` adds the GEM heads, ``pets`` the
table of models, training, planning and the experiments.
"""
