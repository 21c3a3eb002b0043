"""Moved to :mod:`pets.tools.oracle`; this path forwards to it (``python -m pets.oracle`` still works)."""

from pets.tools import forward

forward(__name__, "oracle")
