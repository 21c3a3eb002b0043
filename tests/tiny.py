"""The smallest PETS settings the end-to-end tests run with (16 candidates x 2 particles x 4 steps, 2 iterations;
a 2-member model of 32 units trained 2 epochs; where the terminal value is on, 20 steps per fit), as key=value
overrides."""

TINY_PLANNER = ["planner.population=16", "planner.particles=2", "planner.horizon=4", "planner.iterations=2"]
TINY_MODEL = [
    "model.max_epochs=2",
    "model.hidden_size=32",
    "model.ensemble_size=2",
    "model.num_elites=2",
    "value.steps=20",
]
