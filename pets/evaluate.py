"""Moved to :mod:`pets.tools.evaluate`; this path forwards to it (``python -m pets.evaluate`` still works)."""

from pets.tools import forward

forward(__name__, "evaluate")
