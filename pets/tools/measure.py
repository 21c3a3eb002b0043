"""Measuring primitives of the benchmarks: median wall seconds, GEMM peaks, the model-kernel floor, peak memory, and
the machine and command every benchmark names with its figures.

:mod:`pets.tools.bench` builds its rows from these; nothing here builds a model, a planner or a run
(:func:`kernel_floor` only reads the config's shapes).
"""

from __future__ import annotations

import ctypes
import os
import platform
import resource
import shlex
import statistics
import sys
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import torch
from omegaconf import DictConfig
from torch import Tensor

from pets.planning.particles import PROPAGATION_TABLE
from pets.runs.hardware import cpu_name


def machine(device: torch.device) -> dict[str, Any]:
    """What the figures were measured on: the CPU's model and bf16 ISA, the CPUs this process may use, torch's
    threads, the torch and Python versions, and the GPU where ``device`` is CUDA."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    info: dict[str, Any] = {
        "cpu": cpu_name(),
        "cpus": cpus,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def machine_line(info: dict[str, Any]) -> str:
    """:func:`machine`'s dict as the line a benchmark prints first."""
    threads = f"{info['threads']} torch thread{'s' if info['threads'] != 1 else ''}"
    gpu = f", GPU {info['gpu']}" if "gpu" in info else ""
    return (
        f"machine: {info['cpu']}, {info['cpus']} CPUs usable, {threads}, torch {info['torch']}, "
        f"Python {info['python']}{gpu}"
    )


def command_line(prog: str, argv: list[str] | None = None) -> str:
    """The command that made the figures, ``python -m PROG ARGS`` (``argv``: the arguments given to ``main``; None:
    the process's own)."""
    return shlex.join(["python", "-m", prog, *(sys.argv[1:] if argv is None else argv)])


def model_flops_per_row(in_dim: int, out_dim: int, hidden: int, layers: int) -> int:
    """Multiply-adds x 2 of one member's MLP for one input row (output = mean and log-variance)."""
    dims = [in_dim] + [hidden] * layers + [2 * out_dim]
    return 2 * sum(a * b for a, b in zip(dims[:-1], dims[1:]))


def median_seconds(fn: Callable[[], object], device: torch.device, repeats: int, warmup: int = 1) -> float:
    """Median wall seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones (CUDA: synchronised)."""
    times = []
    for _ in range(warmup + repeats):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times[warmup:])


def matmul_peak_gflops(
    device: torch.device, dtype: torch.dtype = torch.float32, n: int = 2048, repeats: int = 5
) -> float:
    """Measured dense GEMM throughput (median of ``repeats``) for an n x n x n product."""
    a = torch.randn(n, n, device=device).to(dtype)
    b = torch.randn(n, n, device=device).to(dtype)
    return 2 * n**3 / median_seconds(lambda: a @ b, device, repeats) / 1e9


def kernel_floor(
    cfg: DictConfig, input_dim: int, target_dim: int, device: torch.device, repeats: int = 10, bf16: bool = True
) -> dict[str, float]:
    """Seconds per MPC step that the model's own kernels need at the planner's shapes, nothing else.

    One model step of the evaluator is, per layer, one batched GEMM with bias (``torch.baddbmm``, as
    ``dynamics.networks.member_mlp`` runs it) over the propagated members (``num_elites`` members,
    ``ceil(population * particles / members)`` rows each for the ts modes; every member sees all
    ``population`` rows for ``expectation``) plus a SiLU between layers. This times those chained
    layers alone (fp32 and bf16) and the bf16 layers with the SiLUs, on random data (median of
    ``repeats``), and multiplies by the model steps of one CEM planning step (``horizon x iterations``).
    It is the floor the rollout code can reach with these kernels (sampling, head decode, reward and
    planner cost nothing in it), the yardstick for the rows' seconds per step. ``bf16=False``: the fp32 floor only.
    """
    p, mdl = cfg.planner, cfg.model
    members = mdl.num_elites
    rows = PROPAGATION_TABLE[p.propagation].layout.rows_per_member(p.population, p.particles, members)
    dims = [input_dim] + [mdl.hidden_size] * mdl.num_layers + [2 * target_dim]
    gen = torch.Generator(device=device).manual_seed(0)
    steps = p.horizon * p.iterations
    out: dict[str, float] = {}
    for dtype, name in ((torch.float32, "fp32"), (torch.bfloat16, "bf16"))[: 2 if bf16 else 1]:
        x = torch.randn(members, rows, dims[0], generator=gen, device=device).to(dtype)
        ws = [
            (torch.randn(members, a, b, generator=gen, device=device) / a**0.5).to(dtype)
            for a, b in zip(dims[:-1], dims[1:])
        ]
        bs = [torch.zeros(members, 1, b, device=device, dtype=dtype) for b in dims[1:]]

        def forward(x: Tensor, ws: list[Tensor], bs: list[Tensor], silu: bool) -> Tensor:
            h = x
            for i, (w, b) in enumerate(zip(ws, bs)):
                h = torch.baddbmm(b, h, w)
                if silu and i < len(ws) - 1:
                    h = torch.nn.functional.silu(h)
            return h

        for silu in (False, True) if name == "bf16" else (False,):
            seconds = median_seconds(partial(forward, x, ws, bs, silu), device, repeats, warmup=2)
            out[f"{name}_gemm{'_silu' if silu else ''}_seconds_per_step"] = seconds * steps
    return out


def sync(device: torch.device) -> None:
    """Wait for the device's queued kernels (CUDA); nothing on CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _proc_status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


class PeakMemory:
    """Peak memory of a code region in MiB, as ``peak_mib`` after the ``with`` block (what is measured where:
    :mod:`pets.tools.bench`'s docstring)."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.start = 0.0
        self.mode = "cuda" if device.type == "cuda" else "rss"

    def __enter__(self) -> PeakMemory:
        if self.mode == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.start = torch.cuda.memory_allocated(self.device) / 2**20
            return self
        try:
            ctypes.CDLL(None).malloc_trim(0)  # hand free heap memory back, so that the step's own peak shows
        except (OSError, AttributeError):
            pass
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # resets VmHWM to the current VmRSS (Linux >= 4.0)
            rss = _proc_status_kib("VmRSS")
            self.mode = "rss" if rss is not None else "maxrss"
            self.start = (rss or 0) / 1024
        except OSError:
            self.mode = "maxrss"
        if self.mode == "maxrss":
            self.start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        return self

    def __exit__(self, *exc: object) -> None:
        if self.mode == "cuda":
            torch.cuda.synchronize(self.device)
            end = torch.cuda.max_memory_allocated(self.device) / 2**20
        elif self.mode == "rss":
            end = (_proc_status_kib("VmHWM") or 0) / 1024
        else:
            end = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
        self.peak_mib = max(0.0, end - self.start)
