"""Moved to :mod:`pets.tools.openloop`; this path forwards to it (``python -m pets.openloop`` still works)."""

from pets.tools import forward

forward(__name__, "openloop")
