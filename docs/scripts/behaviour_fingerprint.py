"""A fixed-seed fingerprint of the planning and learning paths, to show that a refactor keeps behaviour.

    PYTHONPATH=. python docs/scripts/behaviour_fingerprint.py OUT_DIR [--only NAME,...]

Runs short fixed-seed PETS runs (``run_pets.py``, ``--preset fast``, 2 trials, short episodes, one thread, fp32)
that between them take every planner (CEM, iCEM, MPPI), every propagation (ts1, tsinf, expectation, members),
both candidate kinds (open loop, feedback), a learned terminal value and the delta, GEM and deterministic heads;
then ``pets.collect`` and ``pets.evaluate`` (``eval.json``) on the first run, and ``pets.train`` on the collected
data under both protocols. It also scores random candidates
with a :class:`pets.planning.propagation.TrajectoryEvaluator` in every propagation x candidate kind, and runs every
planner on a fixed objective, hashing the returned tensors (bit identity). Prints one line per item,
``NAME sha256``: ``metrics.csv`` without its timing columns, ``eval.json`` with the run directory's path
replaced. Two trees behave alike when the printed lines are equal (``diff`` the outputs).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
COMMON = ["--preset", "fast", "--trials", "2", "--seed", "3", "--quiet"]
COMMON_KEYS = ["threads=1", "tensorboard=false", "seed_steps=60", "model.max_epochs=5"]
COMMON_KEYS += ["planner.precision=fp32", "model.precision=fp32"]
#: name -> (env, model, extra key=value)
RUNS: dict[str, tuple[str, str, list[str]]] = {
    "ip-delta": ("invertedpendulum", "delta", ["episode_length=30"]),  # MPPI + terminal value, tsinf
    "ip-delta-cem-ts1": ("invertedpendulum", "delta", ["episode_length=20", "planner.name=cem"]),
    "reacher-gem": ("reacher", "gem", ["episode_length=15"]),
    "reacher-deltadet": ("reacher", "delta-det", ["episode_length=15"]),  # expectation
    "idp-feedback": ("inverteddoublependulum", "delta", ["episode_length=15"]),  # CEM gains, members
    "idp-feedback-mppi": ("inverteddoublependulum", "delta", ["episode_length=10", "planner.name=mppi"]),
    "hc-icem": ("halfcheetah", "delta", ["episode_length=12", "planner.name=icem"]),
    "hc-mppi": ("halfcheetah", "delta", ["episode_length=12", "planner.name=mppi"]),
}
RUNS["ip-delta-cem-ts1"][2].append("planner.propagation=ts1")
RUNS["ip-delta-cem-ts1"][2].append("value.enabled=false")
#: Columns that differ run to run (timing): pets.runs.rundir.TIMING_COLUMNS, written out (this script imports no
#: pets module: its runs are subprocesses of the checkout it fingerprints).
TIMING = {"plan_seconds_per_step", "plan_cpu_s", "train_cpu_s", "value_cpu_s", "wall_time_s", "cpu_time_s"}


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def run(args: list[str]) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    done = subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"failed ({done.returncode}): {' '.join(args)}\n{done.stderr[-3000:]}")


def metrics_without_timing(path: Path) -> bytes:
    rows = list(csv.DictReader(path.open()))
    buf = io.StringIO()
    for row in rows:
        buf.write(",".join(f"{k}={v}" for k, v in row.items() if k not in TIMING) + "\n")
    return buf.getvalue().encode()


def online(out: Path, only: set[str] | None) -> None:
    for name, (env, model, keys) in RUNS.items():
        if only is not None and name not in only:
            continue
        run_dir = out / name
        cmd = [sys.executable, "run_pets.py", "--env", env, "--model", model, "--out", str(run_dir), *COMMON]
        run(cmd + COMMON_KEYS + keys)
        text = metrics_without_timing(run_dir / "metrics.csv")
        print(f"{name}/metrics.csv {sha(text)}  {text.decode().splitlines()[-1][:150]}", flush=True)


def evaluation(out: Path) -> None:
    data = out / "ip-random.npz"
    run(
        [sys.executable, "-m", "pets.collect", "--env", "invertedpendulum", "--policy", "random", "--episodes", "3"]
        + ["--max-steps", "40", "--seed", "1", "--threads", "1", "--out", str(data), "--quiet"]
    )
    result = out / "eval.json"
    run(
        [sys.executable, "-m", "pets.evaluate", "--run", str(out / "ip-delta"), "--data", str(data)]
        + ["--horizons", "1,5,10", "--starts", "40", "--mode", "sample", "--threads", "1", "--json", str(result)]
    )
    text = result.read_text().replace(str(out), "OUT").encode()
    print(f"eval.json {sha(text)}", flush=True)


def offline(out: Path) -> None:
    """pets.train on the collected data, under both protocols: metrics.csv and the trained weights."""
    import torch

    for protocol in ("pets", "paper"):
        run_dir = out / f"offline-{protocol}"
        args = ["--data", str(out / "ip-random.npz"), "--model", "delta", "--out", str(run_dir), "--quiet"]
        keys = ["threads=1", "model.precision=fp32", "tensorboard=false", "model.max_epochs=5"]
        keys += ["model.iterations=30"] if protocol == "paper" else []  # the paper's 10k iterations: too long here
        run([sys.executable, "-m", "pets.train", *args, "--protocol", protocol, *keys])
        state = torch.load(run_dir / "checkpoint.pt", weights_only=False)
        weights = b"".join(v.numpy().tobytes() for v in state["model"].values())
        print(f"offline-{protocol} {sha(metrics_without_timing(run_dir / 'metrics.csv') + weights)}", flush=True)


def tensors() -> None:
    """Planned returns of every propagation x candidate kind, and every planner's plan, on an untrained model."""
    sys.path.insert(0, str(ROOT))
    import torch

    import envs
    from pets.config import make_config
    from pets.models import make_model
    from pets.planning.feedback import LinearFeedback
    from pets.planning.planners import PLANNER_CLASSES
    from pets.planning.propagation import TrajectoryEvaluator

    torch.set_num_threads(1)
    spec = envs.get("halfcheetah")
    for head in ("delta", "delta-det"):
        cfg = make_config("halfcheetah", head, "fast", {"planner.precision": "fp32", "model.precision": "fp32"})
        torch.manual_seed(0)
        model = make_model(cfg, spec, torch.device("cpu")).eval()
        obs0 = torch.randn(spec.obs_dim, generator=torch.Generator().manual_seed(1)) * 0.1
        fb = LinearFeedback(spec.obs_dim, spec.action_low, spec.action_high, horizon=7, features=[0, 1, 8])
        for prop in ("ts1", "tsinf", "expectation", "members"):
            for kind, feedback, shape in (("open", None, (9, 6)), ("feedback", fb, fb.shape)):
                ev = TrajectoryEvaluator(
                    model, spec.reward, spec.terminated, particles=4, propagation=prop, feedback=feedback
                )
                cand = torch.rand((11, *shape), generator=torch.Generator().manual_seed(2)) * 2 - 1
                ret = ev(obs0, cand, torch.Generator().manual_seed(3))
                obs, rew = ev.rollout(obs0, cand, torch.Generator().manual_seed(3))
                digest = sha(ret.numpy().tobytes() + obs.numpy().tobytes() + rew.numpy().tobytes())
                print(f"returns/{head}/{prop}/{kind} {digest}", flush=True)
    target = torch.linspace(-0.5, 0.5, 8 * 3).reshape(8, 3)

    def objective(x: torch.Tensor) -> torch.Tensor:
        return -((x - target) ** 2).sum(dim=(1, 2))

    for name, cls in PLANNER_CLASSES.items():
        planner = cls([-1.0] * 3, [1.0] * 3, horizon=8, population=50, iterations=4)
        gen = torch.Generator().manual_seed(5)
        first = planner.plan(objective, None, gen)
        second = planner.plan(objective, torch.cat([first[1:], torch.zeros(1, 3)]), gen)
        print(f"plan/{name} {sha(first.numpy().tobytes() + second.numpy().tobytes())}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--only", help="comma-separated item names (runs, eval, offline, tensors); default all")
    args = parser.parse_args()
    only = set(args.only.split(",")) if args.only else None
    args.out.mkdir(parents=True, exist_ok=True)
    if not only or "tensors" in only:
        tensors()
    online(args.out.resolve(), only - {"tensors", "eval", "offline"} if only else None)
    if not only or "eval" in only:
        evaluation(args.out.resolve())
    if not only or "offline" in only:
        offline(args.out.resolve())


if __name__ == "__main__":
    main()
