"""Ensemble-forward benchmark: autocast's batched bf16 layers against the fused per-member path (dynamics.fused).

    python -m pets.bench_layers [--rows 50,100,200,400,800,1600] [--repeats 15] [--threads 1]

A 7 x 4 x 200 Gaussian ensemble (HalfCheetah delta widths: 24 inputs, 18 targets), 5 elites, under CPU bf16
autocast without autograd and with ``retain_freed_memory`` (as in the planner); for each rows-per-member
count the two paths take turns ``--repeats`` times (10 forwards each) inside one ``fused.cached_weights``
scope. Prints the machine and the command (:func:`pets.tools.measure.machine`), then per count the medians (wall
and process-CPU ms per forward) and the speed-ups, the figures behind ``dynamics.fused.MIN_ROWS``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from dynamics import fused
from dynamics.networks import GaussianEnsemble
from pets.planning.propagation import retain_freed_memory
from pets.runs.hardware import cpu_isa
from pets.tools.cli import OneLineParser, fail, positive_int, set_threads, thread_count
from pets.tools.measure import command_line, machine, machine_line


def row_counts(text: str) -> list[int]:
    """The argparse type of ``--rows``: a comma list of ints >= 1."""
    try:
        return [positive_int(part) for part in text.split(",")]
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be a comma list of ints >= 1, e.g. 50,100, got {text!r}") from None


def _time_paths(
    ens: GaussianEnsemble, x: torch.Tensor, idx: torch.Tensor, repeats: int
) -> tuple[dict[bool, list[float]], dict[bool, list[float]]]:
    """Wall and process-CPU ms per forward of the batched (False) and fused (True) paths, ``repeats`` turns each;
    ``dynamics.fused``'s switches are put back after."""
    wall: dict[bool, list[float]] = {False: [], True: []}
    cpu: dict[bool, list[float]] = {False: [], True: []}
    before = fused.FUSED_CPU_BF16, fused.MIN_ROWS
    try:
        with torch.no_grad(), torch.autocast("cpu", torch.bfloat16), fused.cached_weights():
            for _ in range(repeats):
                for on in (False, True):
                    fused.FUSED_CPU_BF16, fused.MIN_ROWS = on, 0
                    ens(x, idx)
                    t0, c0 = time.perf_counter(), time.process_time()
                    for _ in range(10):
                        ens(x, idx)
                    wall[on].append((time.perf_counter() - t0) / 10 * 1e3)
                    cpu[on].append((time.process_time() - c0) / 10 * 1e3)
    finally:
        fused.FUSED_CPU_BF16, fused.MIN_ROWS = before
    return wall, cpu


def main(argv: list[str] | None = None) -> int:
    ap = OneLineParser(prog="pets.bench_layers", description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=row_counts, default="50,100,200,400,800,1600", help="rows per member, comma list")
    ap.add_argument("--repeats", type=positive_int, default=15, help="turns of each path (default 15; medians)")
    ap.add_argument("--threads", type=thread_count, default=1, help="torch CPU threads (default 1; 0: torch's default)")
    args = ap.parse_args(argv)
    if not fused._AVAILABLE:
        fail(
            "pets.bench_layers",
            f"oneDNN has no fused bf16 linear on this CPU or build (CPU bf16 ISA: {cpu_isa()}): the planner's bf16 "
            "path is the batched one here and there is nothing to compare; run it on a CPU with AVX-512 or AMX",
        )
    set_threads(args.threads)
    retain_freed_memory()
    torch.manual_seed(0)
    ens = GaussianEnsemble(24, 18, ensemble_size=7, hidden_size=200, num_layers=4, num_elites=5)
    idx = torch.tensor([0, 2, 3, 5, 6])
    print(f"{machine_line(machine(torch.device('cpu')))}\ncommand: {command_line('pets.bench_layers', argv)}")
    for rows in args.rows:
        wall, cpu = _time_paths(ens, torch.randn(5, rows, 24), idx, args.repeats)
        batched, per_member = statistics.median(wall[False]), statistics.median(wall[True])
        cpu_batched, cpu_per_member = statistics.median(cpu[False]), statistics.median(cpu[True])
        print(
            f"rows per member {rows:5d}: batched {batched:7.3f} ms, fused per-member {per_member:7.3f} ms, "
            f"speed-up {batched / per_member:.2f}x; process CPU {cpu_batched:7.3f} / {cpu_per_member:7.3f} ms, "
            f"{cpu_batched / cpu_per_member:.2f}x"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
