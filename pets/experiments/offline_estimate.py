"""``pets.compare offline --estimate``: the sweep's CPU-hours projected on this machine before anything runs.

Three kinds of work are projected, each from a short measurement on this machine at the sweep's threads:

- **data sets still to make**: SAC's training (``--policy sac``) as its env steps x the process-CPU seconds of one
  SAC step with its gradient step (the difference of two short trainings, so that start-up cancels), and the
  episodes rolled with a policy (the SAC agent for its test data, a random policy) as their env steps x the
  seconds of one policy and simulator step. A policy that plans (``run:RUN_DIR``) is not projected.
- **runs still to train**: per architecture the run trains (the protocol's search, e.g. the paper's three, or the
  config's one) ``model.iterations`` x the seconds of one gradient step of that architecture
  (:func:`pets.experiments.estimate.train_step_seconds`, eager), measured once per env, arm and architecture.
  Training by epochs with early stopping (``model.iterations=0``, the ``pets`` protocol) grows with the data and
  is not projected.
- **planning still to do** (``--openloop``, ``--closedloop``): its planning steps (one per open-loop episode, of
  the open-loop horizon; one per replanning of each closed-loop step) x the seconds of a planning step with the
  run's planner and the ``--planner-overrides`` (:func:`pets.experiments.estimate.plan_seconds`), on the
  architecture the run has, or for a run still to train the largest its search may pick (said: at most).

Not counted: the evaluation, the validation passes of the training, start-up. A SAC data set in progress counts
the steps its checkpoint leaves; closed-loop episodes that end early cost less.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pets.experiments.arguments import PROG, UsageError
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


@dataclass
class PlanCost:
    """The open- or closed-loop planning of one env and arm with one planner still to do."""

    runs: int = 0
    calls: int = 0  # planning steps: one per open-loop episode (of its horizon), one per replanning in closed loop
    seconds: float = 0.0
    step_s: list[float] = field(default_factory=list)  # per run: its architecture's
    bound: bool = False  # some measured at the largest architecture a run's search may pick: at most

    @property
    def hours(self) -> float:
        return self.seconds / 3600

    def row(self, key: str) -> list[str]:
        low, high = min(self.step_s), max(self.step_s)
        step = fmt(low, 3) if fmt(low, 3) == fmt(high, 3) else f"{fmt(low, 3)}-{fmt(high, 3)}"
        step += " (at most: the largest searched architecture)" if self.bound else ""
        return [key, str(self.runs), f"{self.calls:,}", step, fmt(self.hours, 3)]


@dataclass
class Measures:
    """The measurements a projection multiplies (each given a config or an env; defaults: measured now)."""

    grad: Callable[[DictConfig], float]  # seconds of a gradient step of the config's model
    data: Callable[[str, str, int], tuple[float, float]]  # (env, kind, threads) -> (a SAC step, a rolled step)
    plan: Callable[[DictConfig], float]  # seconds of a planning step of the config's planner and model


def offline_estimate(
    configs: Mapping[str, DictConfig],
    pending: Mapping[str, Sequence[str]],
    architectures: Callable[[str], Sequence[tuple[int, int]]],
    data_jobs: Sequence[tuple[str, Any, tuple]],
    workers: int | None,
    planning: Mapping[str, tuple[int, int]] | None = None,
    planner_overrides: Mapping[str, Any] | None = None,
    measures: Measures | None = None,
    resumed: bool = True,
) -> str:
    """The projection's tables and total.

    ``configs``: {run: config}; ``pending``: {run: what it lacks} (train, eval, openloop_PLANNER,
    closedloop_PLANNER: :func:`pets.experiments.offline_jobs.offline_todo`; runs absent have nothing to do);
    ``architectures(run)``: the ``(hidden_size, num_layers)`` the run trains (or has trained); ``data_jobs``: the
    sweep's jobs of the data sets still to make (``(name, collect_data, (env, [(path, policy, episodes, seed),
    ...], max_steps, progress, threads))``); ``workers``: local workers for the wall time (None: Ray);
    ``planning``: ``{"openloop"|"closedloop": (steps, episodes)}``, ``planner_overrides`` over each run's planner
    (``--planner-overrides``); ``resumed``: a SAC data set counts what its checkpoint leaves (False: no file looked
    at)."""
    m = measures or Measures(_grad_seconds, _data_seconds, _plan_seconds)
    trains = _train_costs(configs, pending, architectures, m.grad)
    plans = _plan_costs(configs, pending, architectures, planning or {}, planner_overrides, m.plan)
    data = _data_costs(data_jobs, m.data, resumed)
    if not trains and not data and not plans:
        return "nothing to train, plan or collect: every data set is there and every run done (evaluation not counted)"
    busy = sum(
        1 for n in configs if any(t == "train" or t.partition("_")[0] in (planning or {}) for t in pending.get(n, ()))
    )
    return _text(data, trains, plans, workers, busy)


def _measured(memo: dict, key: Any, what: str, fn: Callable[[], Any]) -> Any:
    if key not in memo:
        print(f"{PROG} --estimate: measuring {what}", file=sys.stderr)
        memo[key] = fn()
    return memo[key]


def _with_arch(cfg: DictConfig, arch: tuple[int, int]) -> DictConfig:
    return OmegaConf.merge(cfg, {"model": {"hidden_size": arch[0], "num_layers": arch[1]}})


def _train_costs(
    configs: Mapping[str, DictConfig],
    pending: Mapping[str, Sequence[str]],
    architectures: Callable[[str], Sequence[tuple[int, int]]],
    grad: Callable[[DictConfig], float],
) -> dict[str, TrainCost]:
    memo: dict[tuple[str, str, str], float] = {}
    trains: dict[str, TrainCost] = {}
    for name, cfg in configs.items():
        if "train" not in pending.get(name, ()):
            continue
        key = name.rsplit("-s", 1)[0]  # env, arm and data set (pets.experiments.rundirs.run_name)
        train = trains.setdefault(key, TrainCost(iterations=cfg.model.iterations))
        train.runs += 1
        if train.steps or not train.iterations:
            continue
        for arch in architectures(name):
            arch_cfg = _with_arch(cfg, arch)
            memo_key = (cfg.env, cfg.head, OmegaConf.to_yaml(arch_cfg.model))  # an --arm's own model keys too
            what = f"{key} ({arch[0]}x{arch[1]}: a few gradient steps)"
            train.steps[arch] = _measured(memo, memo_key, what, lambda c=arch_cfg: grad(c))
    return trains


def _plan_costs(
    configs: Mapping[str, DictConfig],
    pending: Mapping[str, Sequence[str]],
    architectures: Callable[[str], Sequence[tuple[int, int]]],
    planning: Mapping[str, tuple[int, int]],
    overrides: Mapping[str, Any] | None,
    plan: Callable[[DictConfig], float],
) -> dict[str, PlanCost]:
    from pets.planning.openloop import planning_config

    memo: dict[tuple[str, str, str, str], float] = {}
    plans: dict[str, PlanCost] = {}
    for name, cfg in configs.items():
        for task in pending.get(name, ()):
            kind, _, planner = task.partition("_")
            if kind not in planning:
                continue
            steps, episodes = planning[kind]
            archs = architectures(name)
            arch = max(archs, key=lambda a: a[0] * a[1])  # a run to train: the search's pick is not known yet
            plan_cfg = planning_config(_with_arch(cfg, arch), planner, steps, overrides, closed=kind == "closedloop")
            key = f"{name.rsplit('-s', 1)[0]} {kind} {planner}"
            calls = (-(-steps // plan_cfg.planner.replan_every) if kind == "closedloop" else 1) * episodes
            memo_key = (cfg.env, cfg.head, OmegaConf.to_yaml(plan_cfg.model), OmegaConf.to_yaml(plan_cfg.planner))
            step_s = _measured(memo, memo_key, f"{key} ({arch[0]}x{arch[1]}: a few planning steps)",
                               lambda c=plan_cfg: plan(c))  # fmt: skip
            cost = plans.setdefault(key, PlanCost())
            cost.runs, cost.calls, cost.seconds = cost.runs + 1, cost.calls + calls, cost.seconds + calls * step_s
            cost.step_s.append(step_s)
            cost.bound |= len(archs) > 1
    return plans


def _data_costs(
    data_jobs: Sequence[tuple[str, Any, tuple]], measure: Callable[[str, str, int], tuple[float, float]], resumed: bool
) -> dict[str, DataCost]:
    import envs

    memo: dict[tuple[str, str], tuple[float, float]] = {}
    data: dict[str, DataCost] = {}
    for label, _collect, (env, parts, max_steps, _progress, threads) in data_jobs:
        length = max_steps or envs.get(env).episode_length
        cost = data[label] = DataCost()
        for path, policy, episodes, seed in parts:
            kind = _data_kind(policy)
            if kind == "run":
                cost.projected = False
                continue
            sac_s, rollout_s = _measured(memo, (env, kind), f"{env} data ({kind}: a few steps)",
                                         lambda e=env, k=kind, t=threads: measure(e, k, t))  # fmt: skip
            if policy.startswith("sac:"):  # SAC's training; its test episodes are rolled with its agent (sb3:)
                from pets.data.sb3 import sac_steps_done
                from pets.experiments.offline_data import sac_steps

                steps = sac_steps(policy, "pets")  # the collection's own reading of sac:STEPS (prepare_data)
                try:  # what a stopped collection has done; one it would refuse is refused here with its line
                    done = sac_steps_done(Path(path), envs.get(env), steps, seed, max_steps) if resumed else 0
                except ValueError as err:
                    raise UsageError(str(err)) from None
                cost.sac_steps, cost.sac_s = steps - done, sac_s
            else:
                cost.rollout_steps, cost.rollout_s = cost.rollout_steps + episodes * length, rollout_s
    return data


def _data_kind(policy: str) -> str:
    """``sac`` (SAC's training data, or rolled with a saved SB3 agent: one measurement gives both), ``run`` (a
    PETS run plans), or ``random`` (every other policy: a sampler)."""
    kind = policy.partition(":")[0]
    return {"sb3": "sac"}.get(kind, kind if kind in ("sac", "run") else "random")


def _text(data: dict[str, DataCost], trains: dict[str, TrainCost], plans: dict[str, PlanCost], workers: int | None,
          busy: int) -> str:  # fmt: skip
    """The tables, the total and the wall time (``busy``: the runs with training or planning to do)."""
    tables = (
        (data, ["data set", "SAC env steps", "rolled env steps", "CPU-h"]),
        (trains, ["env, arm (and data set)", "runs to train", "gradient steps", "architectures (s a step)", "CPU-h"]),
        (plans, ["env, arm (and data set), planning", "runs to plan", "planning steps", "s a step", "CPU-h"]),
    )
    blocks = [md_table(header, [c.row(k) for k, c in costs.items()]) for costs, header in tables if costs]
    total_data = sum(c.hours for c in data.values())
    total_runs = sum(c.hours for c in trains.values()) + sum(c.hours for c in plans.values())
    wall = ""
    if workers is not None:
        hours = (total_data / min(workers, len(data)) if data else 0) + (total_runs / min(workers, busy) if busy else 0)
        wall = f" ({fmt(hours, 3)} h of wall time on {workers} worker(s) at best)"
    notes = ["training measured eager"] if trains else []
    if any(not c.iterations for c in trains.values()):
        notes.append("training by epochs not included")
    if any(not c.projected for c in data.values()):
        notes.append("data rolled with a planning policy not included")
    if any(k.split()[1] == "closedloop" for k in plans):
        notes.append("closed-loop episodes that end early cost less")
    notes.append("the evaluation, validation and start-up not counted")
    trained, planned = sum(c.runs for c in trains.values()), len({k.split()[0] for k in plans})
    counts = f"{len(data)} data set(s) to make, {trained} run(s) to train and {planned} arm(s) to plan"
    return "\n\n".join(blocks) + (
        f"\n\n{counts}, about {fmt(total_data + total_runs, 3)} CPU-hours{wall}, measured on this machine now; "
        f"{'; '.join(notes)}"
    )


def _grad_seconds(cfg: DictConfig) -> float:
    from pets.experiments.estimate import train_step_seconds
    from pets.tools.bench import prepare

    return train_step_seconds(cfg, prepare(cfg))


def _plan_seconds(cfg: DictConfig) -> float:
    from pets.experiments.estimate import plan_seconds
    from pets.tools.bench import prepare

    return plan_seconds(cfg, prepare(cfg))


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
    pending: Mapping[str, Sequence[str]] | None,
    planning: Mapping[str, tuple[int, int, Sequence[str]]],
    planner_overrides: Mapping[str, Any] | None,
    workers: int | None,
) -> str:
    """:func:`offline_estimate` of an offline sweep (``pets.experiments.offline``): its ``data_jobs`` and ``pending``
    runs (None: no ``--out``, every run has everything to do and no file is looked at); ``planning``: ``{kind:
    (steps, episodes, planners)}`` of the open- and closed-loop planning it asks for."""
    from pets.experiments.rundirs import run_name

    fresh = pending is None
    if pending is None:
        tasks = ["train", "eval", *(f"{kind}_{p}" for kind, (_, _, planners) in planning.items() for p in planners)]
        pending = dict.fromkeys(configs, tasks)
    archs = {}
    for env in sweep.env_names:
        for model in sweep.models:
            fixed = {"model.hidden_size", "model.num_layers"} & set(sweep.arm(model)[1])  # as train_offline decides
            for name in (run_name(env, model, s, data_seed=d) for s in sweep.seeds for d in sweep.data_seeds):
                cfg = configs[name]
                if "train" not in pending.get(name, ("train",)):  # trained: the architecture it has
                    cfg = OmegaConf.load(sweep.out / "runs" / name / "config.yaml")
                elif not fixed and proto.architectures(env):
                    archs[name] = proto.architectures(env)
                    continue
                archs[name] = ((cfg.model.hidden_size, cfg.model.num_layers),)
    shape = {kind: (steps, episodes) for kind, (steps, episodes, planners) in planning.items() if planners}
    return offline_estimate(
        configs, pending, archs.__getitem__, data_jobs, workers, shape, planner_overrides, resumed=not fresh
    )
