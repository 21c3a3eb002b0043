"""Moved to :mod:`pets.tools.visualize`; this path forwards to it (``python -m pets.visualize`` still works)."""

from pets.tools import forward

forward(__name__, "visualize")
