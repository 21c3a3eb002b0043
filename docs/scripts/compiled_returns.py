"""Do the compiled (inductor) planner returns stay within the bf16 tolerance of the precise path on a real model?

    python docs/scripts/compiled_returns.py RUN_DIR [--candidates 100] [--seed 0]

Loads the model of a run directory (``pets.builder.load_model``), draws ``--candidates`` random action sequences
at the run's horizon, and scores them from the observation of a real reset with the run's propagation and
particles on four paths: fp32 eager (the precise path, the reference), bf16 eager (the CPU default), bf16
compiled and fp32 compiled (``torch.compile`` with inductor). Prints per path the relative L1 difference of the
returns to the reference, the largest difference in units of the reference returns' std, and how many of the
reference's top-10 candidates (CEM's elites at population 100) the path also ranks top-10. The test suite's
bf16 tolerance (``tests/test_propagation.py``) is relative L1 < 5e-3, max < 0.03 std, >= 9 of 10 elites.
The noise generator is reseeded before every path, so every path draws the same noise.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch

from pets import builder
from pets.planning.propagation import TrajectoryEvaluator


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir")
    parser.add_argument("--candidates", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cfg, spec, model = builder.load_model(args.run_dir)
    model.eval()
    env = spec.make()
    obs0 = torch.as_tensor(env.reset(seed=args.seed)[0], dtype=torch.float32)
    gen = torch.Generator().manual_seed(args.seed)
    low, high = (torch.as_tensor(b, dtype=torch.float32) for b in (env.action_space.low, env.action_space.high))
    u = torch.rand(args.candidates, cfg.planner.horizon, spec.act_dim, generator=gen)
    actions = low + (high - low) * u
    paths = {"fp32 eager": ("fp32", False), "bf16 eager": ("bf16", False), "bf16 compiled": ("bf16", True)}
    paths["fp32 compiled"] = ("fp32", True)
    returns, seconds = {}, {}
    for name, (precision, compiled) in paths.items():
        ev = TrajectoryEvaluator(
            model,
            spec.reward,
            spec.terminated,
            particles=cfg.planner.particles,
            propagation=cfg.planner.propagation,
            precision=precision,
            compile=compiled,
        )
        ev(obs0, actions, torch.Generator().manual_seed(1))  # warm-up (compiles)
        t0 = time.process_time()
        returns[name] = ev(obs0, actions, torch.Generator().manual_seed(1)).double()
        seconds[name] = time.process_time() - t0
    ref = returns["fp32 eager"]
    top_ref = set(ref.topk(10).indices.tolist())
    print(
        f"{cfg.env} / {cfg.head}: {args.candidates} candidates, horizon {cfg.planner.horizon}, "
        f"{cfg.planner.particles} particles, {cfg.planner.propagation}; torch {torch.__version__}"
    )
    print(
        "| path | relative L1 to fp32 eager | max diff / std of returns | top-10 shared | rel. L1 to its eager "
        "path | CPU s per call |"
    )
    print("|---|---|---|---|---|---|")
    for name, r in returns.items():
        diff = (r - ref).abs()
        shared = len(top_ref & set(r.topk(10).indices.tolist()))
        eager = returns[name.replace("compiled", "eager")]
        to_eager = float((r - eager).abs().sum() / eager.abs().sum())
        print(
            f"| {name} | {float(diff.sum() / ref.abs().sum()):.2e} | {float(diff.max() / ref.std()):.4f} | "
            f"{shared}/10 | {to_eager:.2e} | {seconds[name]:.4f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
