"""What the machine offers for bf16 matmuls, and ``precision=auto`` (and ``model.compile=auto``) resolved against it.

``auto`` means bfloat16 where the hardware multiplies bf16 natively and it was measured to pay: CPUs with AMX
(``amx_bf16``) or AVX-512 BF16 (``avx512_bf16``) in ``/proc/cpuinfo`` (Linux x86); float32 everywhere else: older
x86, ARM, macOS (bf16 would be emulated, slower than fp32) and CUDA, where this project's small matmuls are
bound by kernel launches, not arithmetic (bf16 eager measured 0.88x of fp32 on an H100 at both presets;
``planner.compile=true`` is what pays there, 2x: docs/performance.md). Resolved once, when the config is made,
so config.yaml records the precision a run used and a resumed run (or the same run on another machine) keeps it.
"""

from __future__ import annotations

import functools
import platform
import sys

import torch

#: Concrete precisions; ``auto`` resolves to one of them.
CONCRETE_PRECISIONS = ("fp32", "bf16")


@functools.lru_cache(maxsize=1)
def _cpuinfo_field(name: str) -> str:
    """The first ``name : value`` of ``/proc/cpuinfo`` ("" off Linux, when unreadable or absent)."""
    if not sys.platform.startswith("linux"):
        return ""
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.partition(":")[2].strip() for line in f if line.startswith(name)), "")
    except OSError:
        return ""


@functools.lru_cache(maxsize=1)
def cpu_flags() -> frozenset[str]:
    """The CPU feature flags of ``/proc/cpuinfo`` (empty off Linux or when unreadable)."""
    return frozenset(_cpuinfo_field("flags").split())


def cpu_name() -> str:
    """The CPU's model name and bf16 ISA, e.g. ``Intel(R) Xeon(R) Processor (AMX)`` (the platform's processor
    name off Linux; ``unknown`` where neither says)."""
    return f"{_cpuinfo_field('model name') or platform.processor() or 'unknown'} ({cpu_isa()})"


def cpu_isa(flags: frozenset[str] | None = None) -> str:
    """The CPU's bf16 matmul ISA in words: ``AMX``, ``AVX-512 BF16`` or ``no native bf16``."""
    flags = cpu_flags() if flags is None else flags
    if "amx_bf16" in flags:
        return "AMX"
    if "avx512_bf16" in flags:
        return "AVX-512 BF16"
    return "no native bf16"


def native_bf16(device_type: str, flags: frozenset[str] | None = None) -> bool:
    """Whether ``device_type`` (``cpu`` or ``cuda``) multiplies bf16 natively (see the module docstring)."""
    if device_type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return cpu_isa(flags) != "no native bf16"


def device_type(device: str) -> str:
    """``cpu`` or ``cuda`` for a config ``device`` value (``auto``: CUDA when torch sees one)."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return "cuda" if device.startswith("cuda") else "cpu"


#: Measured cost of bf16 where it is emulated: one 1600 x 200 x 200 ``baddbmm`` per member (5 members, the
#: HalfCheetah research shapes), AMD EPYC Zen 3 (AVX2 only), 2 threads, torch 2.13: bf16 211 ms, fp32 6.1 ms.
EMULATED_BF16_SLOWDOWN = 35


def emulated_bf16_warning(key: str, precision: str, device: str, flags: frozenset[str] | None = None) -> str | None:
    """A one-line warning when ``key`` (a concrete precision) asks for bf16 on a CPU that has no native bf16
    matmul, else None."""
    if precision != "bf16" or device_type(device) != "cpu" or native_bf16("cpu", flags):
        return None
    return (
        f"{key}=bf16 on a CPU without native bf16 (no amx_bf16 or avx512_bf16 in /proc/cpuinfo): its bf16 matmuls "
        f"are emulated, measured ~{EMULATED_BF16_SLOWDOWN}x slower than fp32 on such a CPU (docs/performance.md); "
        f"use {key}=fp32 or auto (a resumed run keeps the precision it started with: resume it on a CPU with "
        "native bf16, or start a new run)"
    )


def resolve_precision(precision: str, device: str, flags: frozenset[str] | None = None) -> str:
    """``precision`` itself unless ``auto``; ``auto``: ``bf16`` on a CPU with native bf16, else ``fp32`` (CUDA
    included: see the module docstring)."""
    if precision != "auto":
        return precision
    kind = device_type(device)
    return "bf16" if kind == "cpu" and native_bf16(kind, flags) else "fp32"


#: ``model.compile=auto`` turns the compiled training step on for runs of at least this many trials: its one-off
#: cost (the first training compiles: 6-15 CPU-s with inductor's on-disk cache warm, 30-50 s wall cold) is paid back
#: by ~2x faster epochs within the first trials of a run (docs/performance.md, "The default"); shorter runs (quick
#: tries, the test suite's) train eagerly.
AUTO_COMPILE_MIN_TRIALS = 10


def resolve_model_compile(
    compile: bool | None, precision: str, device: str, trials: int, flags: frozenset[str] | None = None
) -> bool:
    """``compile`` itself unless None (``auto``); ``auto``: on where the compiled training step was measured ~2x
    faster, a CPU with native bf16 training in bf16 (``precision``, already resolved), for runs of at least
    :data:`AUTO_COMPILE_MIN_TRIALS` trials; off elsewhere (fp32 CPUs and CUDA: not measured to pay)."""
    if compile is not None:
        return compile
    kind = device_type(device)
    return kind == "cpu" and native_bf16(kind, flags) and precision == "bf16" and trials >= AUTO_COMPILE_MIN_TRIALS
