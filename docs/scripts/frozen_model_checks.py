"""Three checks of an online run's learned model, frozen at its checkpoint (the locomotion gate's diagnosis):

    python docs/scripts/frozen_model_checks.py plan RUN_DIR --variants base margin=0.9 ... [--episodes 4 --steps 300]
    python docs/scripts/frozen_model_checks.py reward RUN_DIR [RUN_DIR ...] --horizons 1 5 15 30
    python docs/scripts/frozen_model_checks.py falls RUN_DIR [RUN_DIR ...] --horizons 1 3 5 10 15

``plan``: MPC in the real env with the run's model and value frozen (``PETS.load``), one row per episode and planner
variant: ``base`` (the run's own planner), ``zero`` (no planner: the zero action every step), ``margin=Z`` (a
predicted torso height above Z also ends a particle, the env's own limit being 1.0), ``pen=X``
(``planner.termination_penalty`` X), ``risk=B`` (``planner.risk_aversion`` B: a candidate scored by the mean minus B
population standard deviations of its particles' returns; rows written before 2026-11-28 16:50 UTC used the sample
standard deviation, B x sqrt(P / (P - 1)) in today's terms, 1.118 B for P = 5 particles), ``novalue`` (no
terminal value), ``planner.KEY=VALUE`` (the agent rebuilt with that planner setting, e.g. ``planner.horizon=5``).
Episode ``e`` resets the env with seed 1000 + e, so every variant meets the same starts.
``reward``: the model's open-loop prediction of the summed reward over H steps along action sequences of the run's
own replay buffer (400 windows within one episode, drawn with seed 0): Pearson correlation with the true sum and the
mean absolute error. ``falls``: for every episode of the buffer that ended in a fall (the env's own termination
function), whether the model's open-loop rollout from H steps before the end, along the recorded actions, ends in
a predicted termination within those H steps (the fraction of falls foreseen, ``recall``). Rows are appended to
``--out`` (one CSV per check).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np
import torch

PLAN_COLUMNS = ["run", "variant", "episode", "steps", "reward", "fell", "height", "cpu_s"]
FALLS_COLUMNS = ["run", "horizon", "falls", "foreseen", "recall"]
REWARD_COLUMNS = ["run", "horizon", "windows", "true_mean", "true_sd", "pred_mean", "corr", "mean_abs_error"]


def _append(path: Path, rows: list[dict], columns: list[str]) -> None:
    new = not path.is_file()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, columns, lineterminator="\n")
        if new:
            writer.writeheader()
        writer.writerows(rows)


def _height(spec) -> int | None:
    """The observation index of the torso's height: the last coordinate of the root's translation (Ant's z,
    Hopper's and HalfCheetah's rootz); None for a body without a root."""
    return None if spec.layout.root is None else spec.layout.group(spec.layout.root[0]).indices[-1]


def _variant(pets, variant: str) -> None:
    """Change the frozen run's evaluator in place as ``variant`` says (module docstring)."""
    run = pets._run
    ev, spec = run.agent.evaluator, run.spec
    z = _height(spec)
    kind, _, arg = variant.partition("=")
    if kind == "margin" and z is None:
        raise SystemExit(f"margin=Z needs a body with a free root (a torso height); {spec.name} has none")
    if kind == "margin":
        top, terminated = float(arg), ev.terminated_fn
        ev.terminated_fn = lambda o, a, n: terminated(o, a, n) | (n[..., z] > top)
    elif kind.startswith("planner."):  # the run's agent rebuilt with one planner setting changed
        from omegaconf import OmegaConf

        from pets.builder import make_agent

        cfg = OmegaConf.merge(run.cfg, OmegaConf.from_dotlist([variant]))
        run.agent = make_agent(cfg, spec, run.model, run.device, run.plan_gen, run.value)
    elif kind == "pen":
        ev.termination_penalty = float(arg)
    elif kind == "novalue":
        ev.terminal_value = None
    elif kind == "risk":  # planner.risk_aversion (the population standard deviation)
        ev.risk_aversion = float(arg)
    elif kind == "zero":  # no planning: the zero action every step (what standing still earns)
        run.agent.act = lambda obs: np.zeros(spec.act_dim, dtype=np.float32)
        run.agent.reset = lambda: None
    elif kind != "base":
        known = "base, zero, margin=Z, pen=X, risk=B, novalue or planner.KEY=VALUE"
        raise SystemExit(f"unknown variant {variant!r}: {known}")


def plan(run_dir: Path, variant: str, episodes: int, steps: int) -> list[dict]:
    from pets.api import PETS

    pets = PETS.load(run_dir)
    _variant(pets, variant)
    agent, spec = pets._run.agent, pets._run.spec
    z = _height(spec)
    env, rows = spec.make(), []
    for e in range(episodes):
        start = time.process_time()
        obs, _ = env.reset(seed=1000 + e)
        agent.reset()
        total, fell, n = 0.0, 0, 0
        while n < steps and not fell:
            obs, reward, terminated, _, _ = env.step(agent.act(obs))
            total, fell, n = total + float(reward), int(terminated), n + 1
        rows.append({"run": run_dir.name, "variant": variant, "episode": e, "steps": n, "reward": round(total, 2),
                     "fell": fell, "height": "" if z is None else round(float(obs[z]), 3),
                     "cpu_s": round(time.process_time() - start, 1)})  # fmt: skip
    return rows


def reward(run_dir: Path, horizon: int, windows: int = 400) -> dict:
    spec, model, obs, act, nxt, ends = _buffer(run_dir)
    ends = ends.numpy()
    rng, starts = np.random.default_rng(0), []
    while len(starts) < windows:
        s = int(rng.integers(len(obs) - horizon))
        if not ends[s : s + horizon - 1].any():
            starts.append(s)
    first = torch.tensor(starts)
    idx = first[:, None] + torch.arange(horizon)[None]
    pred = model.rollout(obs[first], act[idx], "mean")
    before = torch.cat([obs[first][:, None], pred[:, :-1]], dim=1)
    predicted = spec.reward(before, act[idx], pred).sum(1).numpy()
    true = spec.reward(obs[idx], act[idx], nxt[idx]).sum(1).numpy()
    return {"run": run_dir.name, "horizon": horizon, "windows": windows, "true_mean": round(float(true.mean()), 3),
            "true_sd": round(float(true.std()), 3), "pred_mean": round(float(predicted.mean()), 3),
            "corr": round(float(np.corrcoef(predicted, true)[0, 1]), 4),
            "mean_abs_error": round(float(np.abs(predicted - true).mean()), 3)}  # fmt: skip


def _buffer(run_dir: Path):
    """``(spec, model, obs, act, next_obs, episode ends)`` of a run's checkpoint."""
    from omegaconf import OmegaConf

    import envs
    from pets.api import load_model
    from pets.planning.value import episode_ends

    spec = envs.get(OmegaConf.load(run_dir / "config.yaml").env)
    buffer = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=False)["buffer"]
    obs, act, nxt = (torch.as_tensor(buffer[k]).float() for k in ("obs", "act", "next_obs"))
    return spec, load_model(run_dir), obs, act, nxt, episode_ends(obs, nxt)


def falls(run_dir: Path, horizon: int) -> dict:
    spec, model, obs, act, nxt, ends = _buffer(run_dir)
    last = torch.nonzero(ends).flatten()
    fell = spec.terminated(obs[last], act[last], nxt[last]).bool()
    first = torch.cat([torch.zeros(1, dtype=torch.long), last[:-1] + 1])
    seen = total = 0
    for end, start in zip(last[fell].tolist(), first[fell].tolist()):
        s = end - horizon + 1
        if s < start:  # the episode is shorter than the horizon
            continue
        pred = model.rollout(obs[s : s + 1], act[None, s : end + 1], "mean")[0]
        before = torch.cat([obs[s : s + 1], pred[:-1]])
        seen += bool(spec.terminated(before, act[s : end + 1], pred).any())
        total += 1
    recall = round(seen / total, 4) if total else ""
    return {"run": run_dir.name, "horizon": horizon, "falls": total, "foreseen": seen, "recall": recall}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="check", required=True)
    p = sub.add_parser("plan")
    p.add_argument("run_dir", type=Path)
    p.add_argument("--variants", nargs="+", default=["base"])
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--out", type=Path, required=True)
    r = sub.add_parser("reward")
    r.add_argument("run_dirs", type=Path, nargs="+")
    r.add_argument("--horizons", type=int, nargs="+", default=[1, 5, 15, 30])
    r.add_argument("--out", type=Path, required=True)
    f = sub.add_parser("falls")
    f.add_argument("run_dirs", type=Path, nargs="+")
    f.add_argument("--horizons", type=int, nargs="+", default=[1, 3, 5, 10, 15])
    f.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.check == "plan":
        for variant in args.variants:
            rows = plan(args.run_dir, variant, args.episodes, args.steps)
            _append(args.out, rows, PLAN_COLUMNS)
            print(variant, [(r["steps"], r["reward"], r["fell"]) for r in rows], flush=True)
    else:
        check, columns = (reward, REWARD_COLUMNS) if args.check == "reward" else (falls, FALLS_COLUMNS)
        rows = [check(d, h) for d in args.run_dirs for h in args.horizons]
        _append(args.out, rows, columns)
        for row in rows:
            print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
