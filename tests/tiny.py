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


def replacing(overrides: list[str], *new: str) -> list[str]:
    """``overrides`` with each key of ``new`` given its new value (a key given twice is refused)."""
    keys = {item.partition("=")[0] for item in new}
    return [item for item in overrides if item.partition("=")[0] not in keys] + list(new)
