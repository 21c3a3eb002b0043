"""Planning-step benchmark: median seconds per MPC step, achieved model GFLOP/s, machine matmul peak.

    python -m pets.bench --env halfcheetah --model delta [--preset fast] [--device cpu] [--repeats 5]
                         [--json FILE] [key=value ...]

The model is fitted briefly on real random-action transitions first, so the rollouts run through
realistic (normalised, finite) states. Figures are medians over ``--repeats`` timed planning steps
after one warm-up step.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np
import torch

import envs
from pets import builder
from pets.config import ConfigError, make_config, parse_overrides


def model_flops_per_row(in_dim: int, out_dim: int, hidden: int, layers: int) -> int:
    """Multiply-adds x 2 of one member's MLP for one input row (output = mean and log-variance)."""
    dims = [in_dim] + [hidden] * layers + [2 * out_dim]
    return 2 * sum(a * b for a, b in zip(dims[:-1], dims[1:]))


def matmul_peak_gflops(device: torch.device, dtype: torch.dtype = torch.float32, n: int = 2048,
                       repeats: int = 5) -> float:
    """Measured dense GEMM throughput (median of ``repeats``) for an n x n x n product."""
    a = torch.randn(n, n, device=device).to(dtype)
    b = torch.randn(n, n, device=device).to(dtype)
    times = []
    for _ in range(repeats + 1):
        _sync(device)
        t0 = time.perf_counter()
        a @ b
        _sync(device)
        times.append(time.perf_counter() - t0)
    return 2 * n**3 / statistics.median(times[1:]) / 1e9


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def collect_random(spec: envs.EnvSpec, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    env = spec.make()
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    O, A, N = [], [], []
    for _ in range(steps):
        act = rng.uniform(spec.action_low, spec.action_high)
        nxt, _, term, trunc, _ = env.step(act)
        O.append(obs); A.append(act); N.append(nxt)
        obs = nxt if not (term or trunc) else env.reset()[0]
    env.close()
    return np.array(O, np.float32), np.array(A, np.float32), np.array(N, np.float32)


def benchmark(cfg, repeats: int = 5) -> dict[str, float]:
    """Time ``repeats`` planning steps of the configured agent; return the figures as a dict."""
    spec = envs.get(cfg.env)
    device = builder.resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    head = builder.make_head(cfg, spec)
    ensemble = builder.make_ensemble(cfg, head, device)
    trainer = builder.make_trainer(cfg, ensemble, head)
    obs, act, nxt = (torch.as_tensor(x, device=device) for x in collect_random(spec, 400, cfg.seed))
    trainer.max_epochs = 2
    trainer.train(obs, act, nxt, torch.Generator(device=device).manual_seed(cfg.seed))
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    agent = builder.make_agent(cfg, spec, ensemble, head, device, gen)
    start = obs[-1].cpu().numpy()
    times = []
    for _ in range(repeats + 1):
        agent.reset()
        _sync(device)
        t0 = time.perf_counter()
        agent.act(start)
        _sync(device)
        times.append(time.perf_counter() - t0)
    seconds = statistics.median(times[1:])
    p = cfg.planner
    rows = p.population * p.particles * p.horizon * p.iterations
    flops = rows * model_flops_per_row(head.input_dim, head.target_dim, cfg.model.hidden_size, cfg.model.num_layers)
    return {"seconds_per_step": seconds, "model_gflops": flops / seconds / 1e9,
            "peak_gflops": matmul_peak_gflops(device), "model_gflop_per_step": flops / 1e9}


def main(argv: list[str] | None = None) -> int:
    from pets.config import HEADS, PRESETS

    ap = argparse.ArgumentParser(prog="python -m pets.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="halfcheetah")
    ap.add_argument("--model", choices=HEADS, default="delta")
    ap.add_argument("--preset", choices=tuple(PRESETS), default="research")
    ap.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    ap.add_argument("overrides", nargs="*", metavar="key=value")
    args = ap.parse_args(argv)
    try:
        overrides = parse_overrides(args.overrides)
        overrides["device"] = args.device
        cfg = make_config(envs.get(args.env).name, args.model, args.preset, overrides)
    except (ConfigError, ValueError) as err:
        print(f"pets.bench: error: {err}", file=sys.stderr)
        return 2
    p = cfg.planner
    print(f"{cfg.env} / {cfg.head} on {cfg.device} ({torch.get_num_threads()} threads): population {p.population}, "
          f"{p.particles} particles, horizon {p.horizon}, {p.iterations} iterations, ensemble {cfg.model.ensemble_size}"
          f"x{cfg.model.num_layers}x{cfg.model.hidden_size}, propagation {p.propagation}")
    res = benchmark(cfg, args.repeats)
    print(f"seconds per planning step (median of {args.repeats}): {res['seconds_per_step']:.3f}")
    print(f"model work per step: {res['model_gflop_per_step']:.1f} GFLOP -> {res['model_gflops']:.1f} GFLOP/s "
          f"({100 * res['model_gflops'] / res['peak_gflops']:.0f}% of the measured fp32 matmul peak "
          f"{res['peak_gflops']:.1f} GFLOP/s)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
