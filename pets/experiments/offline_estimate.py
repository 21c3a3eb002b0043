"""``pets.compare offline --estimate``: the sweep's CPU-hours projected on this machine before anything runs.

Two kinds of work are projected, each from a short measurement on this machine at the sweep's threads:

- **data sets still to make**: SAC's training (``--policy sac``) as its env steps x the process-CPU seconds of one
  SAC step with its gradient step (the difference of two short trainings, so that start-up cancels), and the
  episodes rolled with a policy (the SAC agent for its test data, a random policy) as their env steps x the
  seconds of one policy and simulator step. A policy that plans (``run:RUN_DIR``) is not projected.
- **runs still to train**: per architecture the run trains (the protocol's search, e.g. the paper's three, or the
  config's one) ``model.iterations`` x the seconds of one gradient step of that architecture
  (:func:`pets.experiments.estimate.train_step_seconds`, eager), measured once per env, arm and architecture.
  Training by epochs with early stopping (``model.iterations=0``, the ``pets`` protocol) grows with the data and
  is not projected.

Not counted: the evaluation, the validation passes of the training, open- and closed-loop planning (said where the
sweep asks for it), start-up. A SAC data set in progress counts the steps its checkpoint leaves.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pets.experiments.arguments import PROG
from pets.experiments.report import fmt, md_table

#: SAC steps of the two measurement trainings (SB3 starts its gradient steps after 100).
SAC_SHORT, SAC_LONG = 150, 450
#: Policy and simulator steps timed per data policy.
ROLLOUT_STEPS = 200


@dataclass
class DataCost:
    """One data set still to make: its SAC steps and rolled steps, and their seconds per step."""

    sac_steps: int = 0
    rollout_steps: int = 0
    sac_s: float = 0.0
    rollout_s: float = 0.0
    projected: bool = True  # False: a policy that plans

    @property
    def hours(self) -> float:
        return (self.sac_steps * self.sac_s + self.rollout_steps * self.rollout_s) / 3600

    def row(self, name: str) -> list[str]:
        sac = f"{self.sac_steps:,} ({fmt(self.sac_s, 3)} s a step)" if self.sac_steps else "-"
        rolled = f"{self.rollout_steps:,} ({fmt(self.rollout_s, 3)} s a step)"
        return [name, sac, rolled, fmt(self.hours, 3) if self.projected else "not projected (a planning policy)"]


@dataclass
class TrainCost:
    """The runs of one env and arm still to train: how many and their gradient steps per architecture."""

    runs: int = 0
    steps: dict[tuple[int, int], float] = field(default_factory=dict)  # architecture -> seconds a gradient step
    iterations: int = 0  # 0: by epochs, not projected

    @property
    def hours(self) -> float:
        return self.runs * self.iterations * sum(self.steps.values()) / 3600

    def row(self, key: str) -> list[str]:
        archs = ", ".join(f"{h}x{n} ({fmt(s, 3)} s)" for (h, n), s in self.steps.items())
        if not self.iterations:
            return [key, str(self.runs), "by epochs", archs or "-", "not projected (epochs)"]
        grads = self.runs * self.iterations * max(1, len(self.steps))
        return [key, str(self.runs), f"{grads:,}", archs, fmt(self.hours, 3)]


def offline_estimate(
    configs: Mapping[str, DictConfig],
    to_train: Collection[str],
    architectures: Callable[[str], Sequence[tuple[int, int]]],
    data_jobs: Sequence[tuple[str, Any, tuple]],
    workers: int | None,
    measure_grad: Callable[[DictConfig], float] | None = None,
    measure_data: Callable[[str, str, int], tuple[float, float]] | None = None,
    resumed: bool = True,
    planning: bool = False,
) -> str:
    """The projection's tables and total.

    ``configs``: {run: config}; ``to_train``: the runs without a trained model; ``architectures(run)``: the
    ``(hidden_size, num_layers)`` the run trains; ``data_jobs``: the sweep's jobs of the data sets still to make
    (``(name, collect_data, (env, [(path, policy, episodes, seed), ...], max_steps, progress, threads))``);
    ``workers``: local workers for the wall time (None: Ray). ``measure_grad(cfg)``: seconds of a gradient step
    of ``cfg``'s model; ``measure_data(env, kind, threads)``: ``(seconds of a SAC step, of a policy and simulator
    step)`` (defaults: measured now, once each). ``resumed``: a SAC data set counts what its checkpoint leaves (False:
    no file looked at). ``planning``: the sweep also plans (``--openloop``, ``--closedloop``), not projected: said."""
    import envs

    grad_memo: dict[tuple[str, str, str], float] = {}
    data_memo: dict[tuple[str, str], tuple[float, float]] = {}
    trains: dict[str, TrainCost] = {}
    for name, cfg in configs.items():
        if name not in to_train:
            continue
        key = name.rsplit("-s", 1)[0]  # env, arm and data set (pets.experiments.rundirs.run_name)
        train = trains.setdefault(key, TrainCost(iterations=cfg.model.iterations))
        train.runs += 1
        if train.steps or not train.iterations:
            continue
        for hidden, layers in architectures(name):
            arch_cfg = OmegaConf.merge(cfg, {"model": {"hidden_size": hidden, "num_layers": layers}})
            memo_key = (cfg.env, cfg.head, OmegaConf.to_yaml(arch_cfg.model))  # an --arm's own model keys too
            if memo_key not in grad_memo:
                print(f"{PROG} --estimate: measuring {key} ({hidden}x{layers}: a few gradient steps)", file=sys.stderr)
                grad_memo[memo_key] = (measure_grad or _grad_seconds)(arch_cfg)
            train.steps[(hidden, layers)] = grad_memo[memo_key]
    data: dict[str, DataCost] = {}
    for label, _collect, (env, parts, max_steps, _progress, data_threads) in data_jobs:
        length = max_steps or envs.get(env).episode_length
        cost = data[label] = DataCost()
        for path, policy, episodes, _seed in parts:
            kind = _data_kind(policy)
            if kind == "run":
                cost.projected = False
                continue
            if (env, kind) not in data_memo:
                print(f"{PROG} --estimate: measuring {env} data ({kind}: a few steps)", file=sys.stderr)
                data_memo[env, kind] = (measure_data or _data_seconds)(env, kind, data_threads)
            sac_s, rollout_s = data_memo[env, kind]
            if policy.startswith("sac:"):  # SAC's training; its test episodes are rolled with its agent (sb3:)
                from pets.data.sb3 import sac_steps_done

                done = sac_steps_done(Path(path)) if resumed else 0  # what a stopped collection has done
                cost.sac_steps, cost.sac_s = int(policy.partition(":")[2]) - done, sac_s
            else:
                cost.rollout_steps, cost.rollout_s = cost.rollout_steps + episodes * length, rollout_s
    if not trains and not data:
        return "nothing to train or collect: every data set is there and every run trained (evaluation not counted)"
    return _text(data, trains, workers, planning)


def _data_kind(policy: str) -> str:
    """``sac`` (SAC's training data, or rolled with a saved SB3 agent: one measurement gives both), ``run`` (a
    PETS run plans), or ``random`` (every other policy: a sampler)."""
    kind = policy.partition(":")[0]
    return {"sb3": "sac"}.get(kind, kind if kind in ("sac", "run") else "random")


def _text(data: dict[str, DataCost], trains: dict[str, TrainCost], workers: int | None, planning: bool) -> str:
    blocks, total_data, total_train = [], 0.0, 0.0
    if data:
        header = ["data set", "SAC env steps", "rolled env steps", "CPU-h"]
        blocks.append(md_table(header, [c.row(n) for n, c in data.items()]))
        total_data = sum(c.hours for c in data.values())
    if trains:
        header = ["env, arm (and data set)", "runs to train", "gradient steps", "architectures (s a step)", "CPU-h"]
        blocks.append(md_table(header, [c.row(k) for k, c in trains.items()]))
        total_train = sum(c.hours for c in trains.values())
    runs = sum(c.runs for c in trains.values())
    total = total_data + total_train
    wall = ""
    if workers is not None:
        hours = (total_data / min(workers, len(data)) if data else 0) + (
            total_train / min(workers, runs) if runs else 0
        )
        wall = f" ({fmt(hours, 3)} h of wall time on {workers} worker(s) at best)"
    notes = ["training measured eager"]
    if any(not c.iterations for c in trains.values()):
        notes.append("training by epochs not included")
    if any(not c.projected for c in data.values()):
        notes.append("data rolled with a planning policy not included")
    notes.append("the evaluation, validation and start-up not counted")
    if planning:
        notes.append("nor the open- and closed-loop planning this sweep asks for, often the larger part (a planning "
                     "step's CPU-seconds: python -m pets.bench)")  # fmt: skip
    return (
        "\n\n".join(blocks)
        + f"\n\n{len(data)} data set{'' if len(data) == 1 else 's'} to make and {runs} run{'' if runs == 1 else 's'} "
        f"to train, about {fmt(total, 3)} CPU-hours{wall}, measured on this machine now; {'; '.join(notes)}"
    )


def _grad_seconds(cfg: DictConfig) -> float:
    from pets.experiments.estimate import train_step_seconds
    from pets.tools.bench import prepare

    parts = prepare(OmegaConf.merge(cfg, {"model": {"iterations": 0}}))  # its 2 warm-up epochs, not the schedule
    return train_step_seconds(cfg, parts)


def _data_seconds(env: str, kind: str, threads: int) -> tuple[float, float]:
    """``(seconds of a SAC step, of a policy and simulator step)`` of ``kind``'s data on ``env``: process CPU."""
    import numpy as np
    import torch

    import envs

    torch.set_num_threads(threads)
    spec = envs.get(env)
    sac_s, agent = 0.0, None
    if kind == "sac":
        from pets.data.sb3 import train_sac

        times = []
        for steps in (SAC_SHORT, SAC_LONG):
            t0 = time.process_time()
            _, agent, _ = train_sac(spec, steps, seed=0, device="cpu")
            times.append(time.process_time() - t0)
        sac_s = (times[1] - times[0]) / (SAC_LONG - SAC_SHORT)
    gym_env = spec.make()
    obs, _ = gym_env.reset(seed=0)
    rng = np.random.default_rng(0)
    low, high = gym_env.action_space.low, gym_env.action_space.high
    per_step = []
    for _ in range(ROLLOUT_STEPS):
        t0 = time.process_time()
        act = agent.predict(obs, deterministic=False)[0] if agent is not None else rng.uniform(low, high)
        obs, _, terminated, truncated, _ = gym_env.step(act)
        if terminated or truncated:
            obs, _ = gym_env.reset()
        per_step.append(time.process_time() - t0)
    gym_env.close()
    return sac_s, statistics.median(per_step)


def sweep_estimate(
    sweep: Any,
    configs: Mapping[str, DictConfig],
    proto: Any,
    data_jobs: Sequence[tuple[str, Any, tuple]],
    workers: int | None,
    configs_only: bool,
    planning: bool,
) -> str:
    """:func:`offline_estimate` of an offline sweep (``pets.experiments.offline``): its runs without a trained model
    and its data sets still to make (``data_jobs``, the sweep's); ``configs_only`` (no ``--out``): every run, no file
    looked at."""
    from pets.experiments.rundirs import run_name

    to_train = {n for n in configs if configs_only or not (sweep.out / "runs" / n / "config.yaml").is_file()}
    archs = {}
    for env in sweep.env_names:
        for model in sweep.models:
            fixed = {"model.hidden_size", "model.num_layers"} & set(sweep.arm(model)[1])  # as train_offline decides
            for name in (run_name(env, model, s, data_seed=d) for s in sweep.seeds for d in sweep.data_seeds):
                cfg = configs[name]
                archs[name] = (() if fixed else proto.architectures(env)) or (
                    (cfg.model.hidden_size, cfg.model.num_layers),
                )
    return offline_estimate(
        configs, to_train, archs.__getitem__, data_jobs, workers, resumed=not configs_only, planning=planning
    )
