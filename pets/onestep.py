"""Moved to :mod:`pets.tools.onestep`; this path forwards to it (``python -m pets.onestep`` still works)."""

from pets.tools import forward

forward(__name__, "onestep")
