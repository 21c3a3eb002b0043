"""GEM: Lie groups (``gem_head.lie``) and the GEM dynamics head (``gem_head.head.GemHead``).

``GemHead`` is re-exported lazily so that ``from gem_head import lie`` stays free of the pets/envs imports.
"""

from __future__ import annotations

from typing import Any

__all__ = ["GemHead", "lie"]


def __getattr__(name: str) -> Any:
    if name == "GemHead":
        from gem_head.head import GemHead

        return GemHead
    if name == "lie":
        import importlib

        return importlib.import_module("gem_head.lie")
    raise AttributeError(f"module 'gem_head' has no attribute {name!r}")
