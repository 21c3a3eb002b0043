"""Ensemble-forward benchmark: autocast's batched bf16 layers against the fused per-member path (dynamics.fused).

    python -m pets.bench_layers [--rows 50,100,200,400,800,1600] [--repeats 15] [--threads 1]

A 7 x 4 x 200 Gaussian ensemble (HalfCheetah delta widths: 24 inputs, 18 targets), 5 elites, under CPU bf16
autocast without autograd and with ``retain_freed_memory`` (as in the planner); for each rows-per-member
count the two paths take turns ``--repeats`` times (10 forwards each) inside one ``fused.cached_weights``
scope. Prints the medians and the speed-up, the figures behind ``dynamics.fused.MIN_ROWS``.
"""

from __future__ import annotations

import statistics
import sys
import time

import torch

from dynamics import fused
from dynamics.networks import GaussianEnsemble
from pets.planning.propagation import retain_freed_memory
from pets.runs.hardware import cpu_isa
from pets.tools.cli import OneLineParser, fail


def main(argv: list[str] | None = None) -> int:
    ap = OneLineParser(prog="pets.bench_layers", description=__doc__.splitlines()[0])
    ap.add_argument("--rows", default="50,100,200,400,800,1600")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    if not fused._AVAILABLE:
        fail(
            "pets.bench_layers",
            f"oneDNN has no fused bf16 linear on this CPU or build (CPU bf16 ISA: {cpu_isa()}): the planner's bf16 "
            "path is the batched one here and there is nothing to compare; run it on a CPU with AVX-512 or AMX",
        )
    torch.set_num_threads(args.threads)
    retain_freed_memory()
    torch.manual_seed(0)
    ens = GaussianEnsemble(24, 18, ensemble_size=7, hidden_size=200, num_layers=4, num_elites=5)
    idx = torch.tensor([0, 2, 3, 5, 6])
    print(f"CPU bf16 ISA: {cpu_isa()}, {args.threads} thread(s); fused path available: {fused._AVAILABLE}")
    for rows in (int(r) for r in args.rows.split(",")):
        x = torch.randn(5, rows, 24)
        ms: dict[bool, list[float]] = {False: [], True: []}
        with torch.no_grad(), torch.autocast("cpu", torch.bfloat16), fused.cached_weights():
            for _ in range(args.repeats):
                for on in (False, True):
                    fused.FUSED_CPU_BF16, fused.MIN_ROWS = on, 0
                    ens(x, idx)
                    t0 = time.perf_counter()
                    for _ in range(10):
                        ens(x, idx)
                    ms[on].append((time.perf_counter() - t0) / 10 * 1e3)
        batched, per_member = statistics.median(ms[False]), statistics.median(ms[True])
        print(
            f"rows per member {rows:5d}: batched {batched:7.3f} ms, fused per-member {per_member:7.3f} ms, "
            f"speed-up {batched / per_member:.2f}x"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
