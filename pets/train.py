"""Moved to :mod:`pets.tools.train`; this path forwards to it (``python -m pets.train`` still works)."""

from pets.tools import forward

forward(__name__, "train")
