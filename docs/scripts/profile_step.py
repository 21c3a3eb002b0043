"""Where a planning step's time goes, by op group: network (its GEMMs and SiLUs apart), head encode and decode,
reward, termination, the rest of the rollout, and the planner outside the rollouts.

    python docs/scripts/profile_step.py --env ant --model gem [--preset fast] [--repeats 5] [key=value ...]

The model is the one ``pets.bench`` builds (briefly fitted on real random transitions); one thread. First the
step's process-CPU seconds without the profiler (median of ``--repeats``), then one profiled round of
``--repeats`` steps with ``torch.profiler``: each group is a ``record_function`` scope around the call that does
it, so its time includes every op it dispatches (the profiler's own per-op cost inflates the groups of many
small ops, so read the shares, not the absolute profiled milliseconds). Under ``planner.compile=true`` the
rollout step is one compiled call: only "rollout (compiled step)" and the planner are told apart.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile, record_function

from pets import builder
from pets.config import make_config, parse_overrides
from pets.tools import bench

GEMM_OPS = ("aten::baddbmm", "aten::bmm", "aten::addmm", "aten::mm", "mkldnn::_linear_pointwise")


def scoped(label: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        with record_function(label):
            return fn(*args, **kwargs)

    return wrapped


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", required=True)
    parser.add_argument("--model", default="gem")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args(argv)
    cfg = make_config(args.env, args.model, args.preset, {"threads": "1", **parse_overrides(args.overrides)})
    parts = bench.prepare(cfg)
    spec, device, model, start = (parts[k] for k in ("spec", "device", "model", "start"))
    agent = builder.make_agent(cfg, spec, model, device, torch.Generator().manual_seed(0))
    ev = agent.evaluator
    if not cfg.planner.compile:  # eager: every part of the rollout step is its own call
        model.inputs = scoped("head encode", model.inputs)
        model.next_obs = scoped("head decode", model.next_obs)
        model.network.forward = scoped("network", model.network.forward)
        ev.reward_fn = scoped("reward", ev.reward_fn)
        if ev.terminated_fn is not None:
            ev.terminated_fn = scoped("termination", ev.terminated_fn)
    ev._run = scoped("rollout", ev._run)
    for _ in range(3):  # warm-up (compiles)
        agent.reset()
        agent.act(start)
    cpu = []
    for _ in range(args.repeats):
        agent.reset()
        t0 = time.process_time()
        agent.act(start)
        cpu.append(time.process_time() - t0)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(args.repeats):
            with record_function("step"):
                agent.reset()
                agent.act(start)
    per = {e.key: e.cpu_time_total / args.repeats / 1e3 for e in prof.key_averages()}
    self_ms = {e.key: e.self_cpu_time_total / args.repeats / 1e3 for e in prof.key_averages()}
    step = per["step"]
    groups = {"rollout": per.get("rollout", 0.0)}
    if not cfg.planner.compile:
        groups = {k: per.get(k, 0.0) for k in ("network", "head encode", "head decode", "reward", "termination")}
        groups["rest of the rollout (noise, guards, state update)"] = per["rollout"] - sum(groups.values())
        gemm = sum(self_ms.get(k, 0.0) for k in GEMM_OPS)
        silu = self_ms.get("aten::silu", 0.0)
        groups = {
            "network: GEMMs": gemm,
            "network: SiLU": silu,
            "network: the rest (normalise, bounds, casts)": groups.pop("network") - gemm - silu,
            **groups,
        }
    else:
        groups = {"rollout (compiled step)": groups["rollout"]}
    groups["planner (sampling, elites, outside the rollouts)"] = step - per["rollout"]
    p = cfg.planner
    print(
        f"{cfg.env} / {cfg.head}, {args.preset} preset ({p.name}, population {p.population}, {p.particles} particles, "
        f"horizon {p.horizon}, {p.iterations} iterations), {p.precision} {'compiled' if p.compile else 'eager'}: "
        f"{statistics.median(cpu):.4f} CPU s per step unprofiled (median of {args.repeats}); profiled {step:.1f} ms"
    )
    print("| part | profiled ms per step | share |")
    print("|---|---|---|")
    for label, ms in groups.items():
        print(f"| {label} | {ms:.1f} | {100 * ms / step:.0f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
