"""PETS: the model table, training, trajectory sampling, planners, the MBRL loop, the offline tools and experiments.

The Python API (docs/api.md): ``pets.PETS`` and ``pets.load_model`` (``pets.api``), imported on first use so that
``import pets.config`` stays cheap.
"""

import importlib
from typing import Any

__all__ = ["PETS", "load_model"]


def __getattr__(name: str) -> Any:
    if name in __all__:  # loaded on first use: pets.api imports torch and the whole library
        return getattr(importlib.import_module("pets.api"), name)
    raise AttributeError(f"module 'pets' has no attribute {name!r}")
