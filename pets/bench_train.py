"""Moved to :mod:`pets.tools.bench_train`; this path forwards to it (``python -m pets.bench_train`` still works)."""

from pets.tools import forward

forward(__name__, "bench_train")
