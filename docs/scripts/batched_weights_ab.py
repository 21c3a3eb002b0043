"""A/B of the planner's weight preparation: once per evaluator call (``dynamics.fused.batched_layers``, the default)
against on every model call (as before it), in one process, interleaved rounds, process-CPU seconds.

    python docs/scripts/batched_weights_ab.py --env ant --model gem [--rounds 12] [key=value ...]

Prints the median CPU seconds per planning step of each (the first 2 rounds dropped as warm-up), their ratio,
and whether the two plans of the first round are bit-identical.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from dynamics import fused
from pets import builder
from pets.config import make_config, parse_overrides
from pets.tools import bench


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", required=True)
    parser.add_argument("--model", default="gem")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--rounds", type=int, default=12)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args(argv)
    cfg = make_config(args.env, args.model, args.preset, {"threads": "1", **parse_overrides(args.overrides)})
    parts = bench.prepare(cfg)
    spec, device, model, start = (parts[k] for k in ("spec", "device", "model", "start"))
    prepared = fused.batched_layers
    ways = {"per call (before)": lambda *a, **k: None, "once per evaluator call": prepared}
    seconds: dict[str, list[float]] = {label: [] for label in ways}
    agents = {label: builder.make_agent(cfg, spec, model, device, torch.Generator().manual_seed(0)) for label in ways}
    plans = {}
    for _ in range(args.rounds):
        for label, fn in ways.items():
            fused.batched_layers = fn
            agent = agents[label]
            agent.reset()
            t0 = time.process_time()
            plan = agent.act(start)
            seconds[label].append(time.process_time() - t0)
            plans.setdefault(label, plan)
    fused.batched_layers = prepared
    med = {label: statistics.median(s[2:]) for label, s in seconds.items()}
    for label, m in med.items():
        print(f"{cfg.env} / {cfg.head} ({cfg.planner.precision}): {label}: {m:.4f} CPU s per step")
    before, after = med.values()
    same = all(bool((a == b).all()) for a, b in zip(*plans.values()))
    print(f"ratio {before / after:.2f}x; first plans bit-identical: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
