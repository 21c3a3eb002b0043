"""The product's one-line warning where a test asks for bf16 on a CPU that emulates it (AVX2 only): expected there,
so asserted rather than left in the suite's output; a CPU with native bf16 gives none."""

import contextlib

import pytest

from pets.runs.hardware import native_bf16


def emulated_bf16_warning():
    """``pytest.warns`` of the emulated-bf16 warning on a CPU without native bf16, else a context that does nothing."""
    if native_bf16("cpu"):
        return contextlib.nullcontext()
    return pytest.warns(RuntimeWarning, match=r"precision=bf16 on a CPU without native bf16")
