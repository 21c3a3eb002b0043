"""Moved to :mod:`pets.tools.bench_layers`; this path forwards to it (``python -m pets.bench_layers`` still works)."""

from pets.tools import forward

forward(__name__, "bench_layers")
