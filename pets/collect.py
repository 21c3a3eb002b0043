"""Moved to :mod:`pets.tools.collect`; this path forwards to it (``python -m pets.collect`` still works)."""

from pets.tools import forward

forward(__name__, "collect")
