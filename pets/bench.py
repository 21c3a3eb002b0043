"""Moved to :mod:`pets.tools.bench`; this path forwards to it (``python -m pets.bench`` still works)."""

from pets.tools import forward

forward(__name__, "bench")
