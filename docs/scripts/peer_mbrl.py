#!/usr/bin/env python
"""This project's PETS beside mbrl-lib's (``mbrl`` 0.2.0, facebookresearch) on the same machine, in one run.

mbrl-lib is no dependency of this package: it lives in a venv of its own, which sees torch and this project
through ``--system-site-packages``::

    python docs/scripts/peer_mbrl.py setup venv-mbrl          # makes the venv, installs the pins below
    venv-mbrl/bin/python docs/scripts/peer_mbrl.py plan        # -> docs/results/peer_planning_step.csv
    venv-mbrl/bin/python docs/scripts/peer_mbrl.py learn --env invertedpendulum   # -> peer_learning_ENV.csv

Run from the repository root (the script puts it first on ``sys.path``). Without mbrl-lib importable every
command but ``setup`` refuses in one line (exit 2) saying how to install it.

``plan``: the HalfCheetah research planning step (population 400, 20 particles, horizon 30, 5 CEM iterations,
ensemble 7 x 4 x 200 SiLU, TS-inf over the 5 elites) of mbrl-lib (``GaussianMLP`` with
``propagation_method="fixed_model"`` = TS-inf, wrapped in its ``OneDTransitionRewardModel`` with its
HalfCheetah observation preprocessing, its ``ModelEnv``, ``CEMOptimizer`` and ``TrajectoryOptimizerAgent`` built by
``create_trajectory_optim_agent_for_model``) and of this project's delta head on its default path and on its fp32
path (``pets.bench.prepare`` / ``pets.bench.time_rows``), all in one process with fixed torch threads. Both models
are fitted briefly on the same 400 random HalfCheetah-v5 transitions (2 epochs) so the rollouts run through
realistic normalised states. The three rows take turns in every round (a change in machine load hits them alike);
each round times one fresh-plan step per row (the project's rows after an untimed warm-up step of
``time_rows``); the CSV gives medians over the rounds of wall and process-CPU seconds, and the machine.
mbrl-lib's timed steps run after this project's agents are built, so under this project's process-wide glibc
allocator setting (``pets.planning.propagation.retain_freed_memory``); ``profile`` times mbrl-lib's step in a process of
its own without and then with that setting, and profiles one step (torch.profiler, ops by self CPU time).

``learn``: mbrl-lib's PETS example loop (``mbrl.algorithms.pets.train``) vs ``run_pets.py --model delta`` at
matched settings (ensemble, elites, CEM population/iterations/elite ratio/momentum, horizon, particles, TS-inf,
seed steps, trials, episode length, batch size, learning rate, epochs, patience, hold-out ratio), paired seeds,
each run a child process of its own (one at a time, its CPU seconds from the kernel's rusage). Both arms get the
same env reset seeds (this project's ``episode_reset_seed``), so pair ``s`` starts its trials from the same states.

Shims that mbrl-lib 0.2.0 needs on today's stack (none edits its files):

- versions: mbrl pins ``hydra-core==1.0.3``, ``omegaconf<2.1`` and ``gymnasium==0.26.3``. It is installed with
  ``--no-deps`` beside the machine's torch and gymnasium 1.x, with ``hydra-core 1.3.8`` whose parser needs
  ``antlr4-python3-runtime==4.9.3``, hence ``omegaconf==2.3.0`` (the newest built on that antlr; this project asks
  for ``omegaconf>=2.3``) in the venv, shadowing the machine's.
- its wheel lacks ``examples/conf/action_optimizer/cem.yaml`` and ``env/assets/half_cheetah.xml``: the CEM config
  is written out here with mbrl's keys; the HalfCheetah data for ``plan`` come from gymnasium's HalfCheetah-v5,
  turned into mbrl's PETS-HalfCheetah observation (x velocity first, then qpos[1:], qvel) so that its own
  ``reward_fns.halfcheetah``, ``HalfCheetahEnv.preprocess_fn`` and ``no_delta_list=[0]`` apply unchanged.
- ``learn``: a gymnasium wrapper around the env given to ``mbrl.algorithms.pets.train`` that seeds every reset
  with this project's reset seeds, times every episode (wall and process CPU) and stops the loop after the
  requested number of trials (mbrl's loop stops on env steps, not trials).
- hydra >= 1.1 instantiates nested configs itself (hydra 1.0 did not): the model config carries
  ``_recursive_: False`` so that ``GaussianMLP`` gets its ``activation_fn_cfg`` and ``TrajectoryOptimizerAgent``
  its ``optimizer_cfg`` as configs, as mbrl expects.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

PROG = "peer_mbrl.py"
MBRL_VERSION = "0.2.0"
#: What ``setup`` installs into the venv, all with ``--no-deps`` (see the module docstring).
PINS = (f"mbrl=={MBRL_VERSION}", "hydra-core==1.3.8", "omegaconf==2.3.0", "antlr4-python3-runtime==4.9.3", "termcolor")
RESULTS = ROOT / "docs" / "results"


class MbrlMissing(RuntimeError):
    """mbrl-lib (the pinned version) is not importable in this interpreter."""


def install_hint() -> str:
    return (
        f"mbrl-lib (mbrl {MBRL_VERSION}) is not importable with {sys.executable}; install it with "
        f"`python docs/scripts/{PROG} setup VENV` and run `VENV/bin/python docs/scripts/{PROG} ...`"
    )


def require_mbrl() -> Any:
    """The ``mbrl`` module, or :class:`MbrlMissing` with the one-line install hint."""
    try:
        import mbrl
    except ImportError as err:
        raise MbrlMissing(install_hint()) from err
    if getattr(mbrl, "__version__", None) != MBRL_VERSION:
        raise MbrlMissing(f"found mbrl {getattr(mbrl, '__version__', '?')}, need {MBRL_VERSION}; {install_hint()}")
    return mbrl


# ---------------------------------------------------------------------------------------------- machine
def machine() -> dict[str, Any]:
    """The CPU (lscpu's model name, family/model from /proc/cpuinfo), its bf16 flags, load, torch threads."""
    import torch

    from pets.runs.hardware import cpu_isa

    info: dict[str, str] = {}
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        info = {k.strip(): v.strip() for k, v in (ln.split(":", 1) for ln in out.splitlines() if ":" in ln)}
    except OSError:
        pass
    flags: set[str] = set()
    fam = mod = ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, val = line.partition(":")
                key = key.strip()
                if key == "flags" and not flags:
                    flags = set(val.split())
                elif key == "cpu family" and not fam:
                    fam = val.strip()
                elif key == "model" and not mod:
                    mod = val.strip()
    except OSError:
        pass
    return {
        "cpu": info.get("Model name", platform.processor() or "unknown"),
        "cpu_family_model": f"{fam}/{mod}" if fam else "",
        "cores": os.cpu_count(),
        "avx512_bf16": "avx512_bf16" in flags,
        "amx_bf16": "amx_bf16" in flags,
        "bf16_isa": cpu_isa(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "load_1min": round(os.getloadavg()[0], 2),
    }


def _utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


# ---------------------------------------------------------------------------------------------- mbrl side
def cem_config(*, population: int, iterations: int, elite_ratio: float, alpha: float) -> dict[str, Any]:
    """mbrl-lib's action_optimizer/cem config with the given CEM settings (bounds filled in by its agent)."""
    return {
        "_target_": "mbrl.planning.CEMOptimizer",
        "num_iterations": iterations,
        "elite_ratio": elite_ratio,
        "population_size": population,
        "alpha": alpha,
        "lower_bound": "???",
        "upper_bound": "???",
        "return_mean_elites": True,
        "device": "cpu",
        "clipped_normal": False,
    }


def mbrl_config(
    *,
    ensemble: int,
    elites: int,
    population: int,
    iterations: int,
    elite_ratio: float,
    alpha: float,
    horizon: int,
    particles: int,
    lr: float,
    batch_size: int,
    epochs: int,
    patience: int,
    validation_ratio: float,
    weight_decay: float = 0.0,
    learned_rewards: bool = False,
    obs_process_fn: str | None = None,
    no_delta_list: list[int] | None = None,
    trial_length: int = 1000,
    freq_train_model: int = 1000,
    initial_exploration_steps: int = 1000,
    num_steps: int = 1000,
    seed: int = 0,
) -> Any:
    """The config mbrl-lib's PETS reads (its examples/conf main + algorithm/pets + dynamics_model/
    gaussian_mlp_ensemble + an override file + action_optimizer/cem), as one DictConfig, with TS-inf
    (``propagation_method: fixed_model``) instead of its default TS1 (``random_model``)."""
    import omegaconf

    overrides: dict[str, Any] = {
        "learned_rewards": learned_rewards,
        "trial_length": trial_length,
        "num_steps": num_steps,
        "num_elites": elites,
        "model_lr": lr,
        "model_wd": weight_decay,
        "model_batch_size": batch_size,
        "validation_ratio": validation_ratio,
        "freq_train_model": freq_train_model,
        "patience": patience,
        "num_epochs_train_model": epochs,
        "planning_horizon": horizon,
    }
    if obs_process_fn:
        overrides["obs_process_fn"] = obs_process_fn
    if no_delta_list:
        overrides["no_delta_list"] = no_delta_list
    cem = cem_config(population=population, iterations=iterations, elite_ratio=elite_ratio, alpha=alpha)
    return omegaconf.OmegaConf.create(
        {
            "seed": seed,
            "device": "cpu",
            "debug_mode": False,
            "action_optimizer": cem,
            "algorithm": {
                "name": "pets",
                "agent": {
                    "_target_": "mbrl.planning.TrajectoryOptimizerAgent",
                    "_recursive_": False,  # the agent fills the optimizer's bounds before it instantiates it
                    "action_lb": "???",
                    "action_ub": "???",
                    "planning_horizon": horizon,
                    "optimizer_cfg": cem,
                    "replan_freq": 1,
                    "verbose": False,
                },
                "normalize": True,
                "normalize_double_precision": True,
                "target_is_delta": True,
                "initial_exploration_steps": initial_exploration_steps,
                "dataset_size": initial_exploration_steps + num_steps,  # the replay buffer's capacity
                "freq_train_model": freq_train_model,
                "learned_rewards": learned_rewards,
                "num_particles": particles,
            },
            "dynamics_model": {
                "_target_": "mbrl.models.GaussianMLP",
                "_recursive_": False,  # hydra >= 1.1 would build the SiLU itself; GaussianMLP wants its config
                "device": "cpu",
                "num_layers": 4,
                "in_size": "???",
                "out_size": "???",
                "ensemble_size": ensemble,
                "hid_size": 200,
                "deterministic": False,
                "propagation_method": "fixed_model",
                "learn_logvar_bounds": False,
                "activation_fn_cfg": {"_target_": "torch.nn.SiLU"},
            },
            "overrides": overrides,
        }
    )


def halfcheetah_mbrl_data(obs: Any, act: Any, nxt: Any, dt: float) -> tuple[Any, Any, Any]:
    """mbrl's PETS-HalfCheetah observations from gymnasium HalfCheetah-v5 transitions with root x at index 0
    (this project's layout): entry 0 becomes the x velocity of the step that led to the state (0 at a reset, as
    mbrl's env starts with ``prev_qpos = qpos``), the rest stays (qpos[1:], qvel)."""
    import numpy as np

    nxt_m = nxt.copy()
    nxt_m[:, 0] = (nxt[:, 0] - obs[:, 0]) / dt
    obs_m = obs.copy()
    obs_m[:, 0] = 0.0
    cont = np.all(obs[1:] == nxt[:-1], axis=1)  # the same episode: the previous step's next state
    obs_m[1:][cont] = nxt_m[:-1][cont]
    return obs_m.astype(np.float32), act.astype(np.float32), nxt_m.astype(np.float32)


def mbrl_planner(cfg: Any, obs: Any, act: Any, nxt: Any, reward_fn: Any, term_fn: Any, seed: int) -> Any:
    """mbrl-lib's PETS agent on a model fitted (mbrl's own trainer, ``cfg.overrides`` epochs) to the transitions."""
    import gymnasium
    import mbrl.models
    import mbrl.planning
    import mbrl.util
    import mbrl.util.common
    import numpy as np
    import torch

    obs_space = gymnasium.spaces.Box(-np.inf, np.inf, shape=obs.shape[1:], dtype=np.float32)
    act_space = gymnasium.spaces.Box(-1.0, 1.0, shape=act.shape[1:], dtype=np.float32)
    model = mbrl.util.common.create_one_dim_tr_model(cfg, obs_space.shape, act_space.shape)
    buffer = mbrl.util.ReplayBuffer(len(obs), obs_space.shape, act_space.shape, rng=np.random.default_rng(seed))
    for o, a, n in zip(obs, act, nxt):
        buffer.add(o, a, n, 0.0, False, False)
    trainer = mbrl.models.ModelTrainer(model, optim_lr=cfg.overrides.model_lr, weight_decay=cfg.overrides.model_wd)
    mbrl.util.common.train_model_and_save_model_and_data(model, trainer, cfg.overrides, buffer, work_dir=None)
    space = type("Spaces", (), {"observation_space": obs_space, "action_space": act_space})()
    model_env = mbrl.models.ModelEnv(
        space, model, term_fn, reward_fn, generator=torch.Generator(device="cpu").manual_seed(seed)
    )
    agent = mbrl.planning.create_trajectory_optim_agent_for_model(
        model_env, cfg.algorithm.agent, num_particles=cfg.algorithm.num_particles
    )
    agent.mbrl_model = model  # for the checks below
    return agent


# ---------------------------------------------------------------------------------------------- plan
def halfcheetah_pair(threads: int) -> dict[str, Any]:
    """The research config (delta, CPU, ``threads``), this project's fitted model and start state
    (``pets.bench.prepare``), and mbrl-lib's agent on a model fitted to the same 400 random transitions, with its
    observation of the same start state; ``elites``: the members mbrl propagates."""
    require_mbrl()
    import mbrl.env.reward_fns
    import mbrl.env.termination_fns
    import numpy as np
    import torch

    from pets.config import make_config
    from pets.data.rollout import collect_random
    from pets.tools import bench

    torch.set_num_threads(threads)
    torch.set_num_interop_threads(threads)
    cfg = make_config("halfcheetah", "delta", "research", {"device": "cpu", "threads": threads})
    p, m = cfg.planner, cfg.model
    parts = bench.prepare(cfg)  # the project's model, fitted on 400 random transitions (seed cfg.seed)
    spec = parts["spec"]
    obs, act, nxt = collect_random(spec, 400, cfg.seed)  # the same transitions, for mbrl's model
    obs_m, act_m, nxt_m = halfcheetah_mbrl_data(obs, act, nxt, spec.dt)
    start_m = nxt_m[-2]  # mbrl's observation of the state parts["start"] (= obs[-1] = nxt[-2])
    assert np.array_equal(parts["start"], nxt[-2]), "start state mismatch"
    mcfg = mbrl_config(
        ensemble=m.ensemble_size,
        elites=m.num_elites,
        population=p.population,
        iterations=p.iterations,
        elite_ratio=p.elites,
        alpha=p.alpha,
        horizon=p.horizon,
        particles=p.particles,
        lr=m.lr,
        batch_size=m.batch_size,
        epochs=2,
        patience=5,
        validation_ratio=0.0,
        obs_process_fn="mbrl.env.pets_halfcheetah.HalfCheetahEnv.preprocess_fn",
        no_delta_list=[0],
        seed=cfg.seed,
    )
    torch.manual_seed(cfg.seed)
    agent = mbrl_planner(
        mcfg,
        obs_m,
        act_m,
        nxt_m,
        mbrl.env.reward_fns.halfcheetah,
        mbrl.env.termination_fns.no_termination,
        cfg.seed,
    )
    model = agent.mbrl_model.model
    elites = len(model.elite_models) if model.elite_models is not None else len(model)
    if (p.population * p.particles) % elites:
        raise SystemExit(f"{PROG}: population x particles must be a multiple of mbrl's {elites} elites")
    return {"cfg": cfg, "parts": parts, "agent": agent, "start_m": start_m, "elites": elites}


def plan(args: argparse.Namespace) -> int:
    from pets.tools import bench

    pair = halfcheetah_pair(args.threads)
    mach = machine()
    print(f"{_utc_now()}: {mach}", flush=True)
    cfg, parts, agent, start_m, elites = (pair[k] for k in ("cfg", "parts", "agent", "start_m", "elites"))
    model = agent.mbrl_model.model
    p, m = cfg.planner, cfg.model
    rows = [
        (f"gem-pets default: {p.name} {p.precision} {'compiled' if p.compile else 'eager'}", {}),
        ("gem-pets fp32: cem fp32 eager", {"name": "cem", "precision": "fp32", "compile": False}),
    ]
    t0 = time.perf_counter()
    agent.reset()
    agent.act(start_m)  # warm-up
    mbrl_first = time.perf_counter() - t0
    times: dict[str, dict[str, list[float]]] = {}
    first: dict[str, float] = {"mbrl-lib 0.2.0: CEMOptimizer fp32 eager": mbrl_first}
    for r in range(args.repeats):
        for res in bench.time_rows(cfg, rows, repeats=1, parts=parts):
            t = times.setdefault(res["label"], {"wall": [], "cpu": []})
            t["wall"].append(res["seconds_per_step"])
            t["cpu"].append(res["cpu_seconds_per_step"])
            first.setdefault(res["label"], res["first_step_seconds"])
        agent.reset()
        t0, c0 = time.perf_counter(), time.process_time()
        agent.act(start_m)
        t = times.setdefault("mbrl-lib 0.2.0: CEMOptimizer fp32 eager", {"wall": [], "cpu": []})
        t["wall"].append(time.perf_counter() - t0)
        t["cpu"].append(time.process_time() - c0)
        print(f"round {r + 1}/{args.repeats}: " + ", ".join(f"{k} {v['wall'][-1]:.3f} s" for k, v in times.items()))
    mach_end = machine()
    peer = times["mbrl-lib 0.2.0: CEMOptimizer fp32 eager"]
    peer_wall, peer_cpu = statistics.median(peer["wall"]), statistics.median(peer["cpu"])
    head = parts["model"].head
    inputs = {
        "gem-pets": head.input_dim,
        "mbrl-lib": model.in_size,
    }
    out = []
    for label, t in times.items():
        wall, cpu = statistics.median(t["wall"]), statistics.median(t["cpu"])
        impl = "mbrl-lib" if label.startswith("mbrl") else "gem-pets"
        out.append(
            {
                "date_utc": _utc_now(),
                "command": f"{Path(sys.executable).parent.parent.name}/bin/python docs/scripts/{PROG} plan "
                f"--repeats {args.repeats} --threads {args.threads}",
                "row": label,
                "env": "HalfCheetah-v5",
                "population": p.population,
                "particles": p.particles,
                "horizon": p.horizon,
                "iterations": p.iterations,
                "ensemble": f"{m.ensemble_size}x{m.num_layers}x{m.hidden_size} silu",
                "propagated_members": elites,
                "model_input_dim": inputs[impl],
                "steps": len(t["wall"]),
                "wall_s_median": round(wall, 4),
                "cpu_s_median": round(cpu, 4),
                "wall_s_min": round(min(t["wall"]), 4),
                "wall_s_max": round(max(t["wall"]), 4),
                "first_step_s": round(first[label], 3),
                "mbrl_over_this_wall": round(peer_wall / wall, 2),
                "mbrl_over_this_cpu": round(peer_cpu / cpu, 2),
                "cpu": mach["cpu"],
                "cpu_family_model": mach["cpu_family_model"],
                "cores": mach["cores"],
                "avx512_bf16": mach["avx512_bf16"],
                "amx_bf16": mach["amx_bf16"],
                "torch": mach["torch"],
                "threads": args.threads,
                "load_1min_start": mach["load_1min"],
                "load_1min_end": mach_end["load_1min"],
            }
        )
    write_csv(Path(args.out), out)
    for r in out:
        print(
            f"{r['row']:<45} wall {r['wall_s_median']:.3f} s  cpu {r['cpu_s_median']:.3f} s  "
            f"mbrl/this wall {r['mbrl_over_this_wall']:.2f} cpu {r['mbrl_over_this_cpu']:.2f}"
        )
    print(f"wrote {args.out}")
    return 0


def profile(args: argparse.Namespace) -> int:
    """mbrl-lib's planning step at the ``plan`` shapes in a process where this project built no agent: median
    wall/CPU seconds and minor page faults of ``--repeats`` steps with glibc's default allocator settings, then
    as many with this project's ``pets.planning.propagation.retain_freed_memory()`` (process-wide; ``plan`` runs
    mbrl-lib after this project's agents, so with it), then torch.profiler over one more step: the ops by self CPU
    time."""
    import torch

    from pets.planning.propagation import retain_freed_memory

    pair = halfcheetah_pair(args.threads)
    agent, start_m = pair["agent"], pair["start_m"]
    agent.reset()
    agent.act(start_m)  # warm-up
    print(f"{_utc_now()}: {machine()}")

    def timed(label: str) -> None:
        wall, cpu, faults = [], [], []
        for _ in range(args.repeats):
            agent.reset()
            f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            t0, c0 = time.perf_counter(), time.process_time()
            agent.act(start_m)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
        print(
            f"mbrl-lib step, {label}: wall {statistics.median(wall):.3f} s, cpu {statistics.median(cpu):.3f} s, "
            f"minor page faults {statistics.median(faults):.0f} (medians of {args.repeats})",
            flush=True,
        )

    timed("glibc defaults")
    print(f"retain_freed_memory() in effect: {retain_freed_memory()}")
    timed("with retain_freed_memory()")
    agent.reset()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        agent.act(start_m)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.rows))
    return 0


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


# ---------------------------------------------------------------------------------------------- learn
#: Per env: mbrl-lib's example override values that have no counterpart in this project's config (weight decay),
#: the time-to-threshold mark (pets.experiments.studies.online.THRESHOLDS; InvertedPendulum's is its
#: maximum, i.e. the episode length), and mbrl's own reward/termination functions where it has them for the env.
LEARN_ENVS: dict[str, dict[str, Any]] = {
    "invertedpendulum": {"weight_decay": 3.3e-5, "mbrl_fns": ("inverted_pendulum", "inverted_pendulum")},
    "reacher": {"weight_decay": 1.7e-4, "mbrl_fns": None},
    # mbrl's own PETS-HalfCheetah: its observation (x velocity first, :func:`halfcheetah_velocity_obs`), reward,
    # preprocessing and weight decay (examples/conf/overrides/pets_halfcheetah.yaml)
    "halfcheetah": {"weight_decay": 1e-4, "mbrl_fns": ("halfcheetah", "no_termination")},
}
#: mbrl-lib's settings of its PETS-HalfCheetah example that its loop needs beside the matched ones.
HALFCHEETAH_MBRL = {
    "obs_process_fn": "mbrl.env.pets_halfcheetah.HalfCheetahEnv.preprocess_fn",
    "no_delta_list": [0],
}


def halfcheetah_velocity_obs(env: Any, dt: float) -> Any:
    """HalfCheetah-v5 with root x at index 0 (this project's layout) seen as mbrl's PETS-HalfCheetah env, online:
    entry 0 becomes the x velocity of the step that led to the state, 0 at a reset (the conversion of
    :func:`halfcheetah_mbrl_data`); rewards, terminations and the other entries pass through."""
    import gymnasium
    import numpy as np

    class VelocityObs(gymnasium.Wrapper):
        def reset(self, **kwargs: Any) -> Any:
            obs, info = self.env.reset(**kwargs)
            self._x = float(obs[0])
            out = np.array(obs, dtype=np.float32)
            out[0] = 0.0
            return out, info

        def step(self, action: Any) -> Any:
            obs, reward, terminated, truncated, info = self.env.step(action)
            out = np.array(obs, dtype=np.float32)
            out[0] = (float(obs[0]) - self._x) / dt
            self._x = float(obs[0])
            return out, reward, terminated, truncated, info

    return VelocityObs(env)


class TrialsDone(Exception):
    """Raised by :class:`TrialWrapper` at the reset after the last requested trial: ends mbrl's loop."""


def trial_wrapper(env: Any, seed: int, trials: int, seed_steps: int) -> Any:
    """The env for ``mbrl.algorithms.pets.train``: every reset seeded with this project's reset seeds (seed-phase
    episodes ``episode_reset_seed(seed, SEED_PHASE + i)``, trial ``t`` ``episode_reset_seed(seed, t)``, as
    ``pets.loop`` does), every episode timed (wall and process CPU, reset to reset: the training that mbrl's loop
    runs at the start of a trial counts in that trial), :class:`TrialsDone` at the reset after ``trials`` trials."""
    import gymnasium

    from pets.loop import SEED_PHASE, episode_reset_seed

    class TrialWrapper(gymnasium.Wrapper):
        def __init__(self, env: Any) -> None:
            super().__init__(env)
            self.steps = 0
            self.episodes: list[dict[str, Any]] = []

        def _close(self) -> None:
            if self.episodes and "wall_s" not in self.episodes[-1]:
                ep = self.episodes[-1]
                ep["wall_s"] = time.perf_counter() - ep.pop("_t0")
                ep["cpu_s"] = time.process_time() - ep.pop("_c0")
                ep["env_steps"] = self.steps

        def reset(self, **kwargs: Any) -> Any:
            self._close()
            seeding = self.steps < seed_steps
            done = [e for e in self.episodes if e["phase"] == ("seed" if seeding else "trial")]
            if not seeding and len(done) >= trials:
                raise TrialsDone
            index = SEED_PHASE + len(done) if seeding else len(done)
            kwargs["seed"] = episode_reset_seed(seed, index)
            self.episodes.append(
                {
                    "phase": "seed" if seeding else "trial",
                    "reward": 0.0,
                    "length": 0,
                    "_t0": time.perf_counter(),
                    "_c0": time.process_time(),
                }
            )
            return self.env.reset(**kwargs)

        def step(self, action: Any) -> Any:
            out = self.env.step(action)
            self.steps += 1
            self.episodes[-1]["reward"] += float(out[1])
            self.episodes[-1]["length"] += 1
            return out

    return TrialWrapper(env)


def learn_settings(args: argparse.Namespace) -> dict[str, Any]:
    return {
        k: getattr(args, k)
        for k in (
            "trials",
            "episode_length",
            "seed_steps",
            "ensemble",
            "population",
            "iterations",
            "elite_ratio",
            "alpha",
            "horizon",
            "particles",
            "epochs",
            "patience",
            "batch_size",
            "lr",
            "holdout",
            "threads",
        )
    }


def mbrl_run(args: argparse.Namespace) -> int:
    """One run of mbrl-lib's PETS loop (a child process of ``learn``); writes its episodes as JSON."""
    import tempfile

    require_mbrl()
    import gymnasium
    import mbrl.algorithms.pets
    import mbrl.env.reward_fns
    import mbrl.env.termination_fns
    import numpy as np
    import torch

    import envs

    torch.set_num_threads(args.threads)
    torch.set_num_interop_threads(args.threads)
    spec = envs.get(args.env)
    fns = LEARN_ENVS[spec.name]["mbrl_fns"]
    if fns:
        reward_fn = getattr(mbrl.env.reward_fns, fns[0])
        term_fn = getattr(mbrl.env.termination_fns, fns[1])
    else:  # Reacher-v5: mbrl has none for gymnasium's observation; this project's reads (act, next_obs) only

        def reward_fn(act: Any, next_obs: Any) -> Any:
            return spec.reward_fn(next_obs, act, next_obs).view(-1, 1)

        term_fn = mbrl.env.termination_fns.no_termination
        x = torch.randn(8, spec.obs_dim)
        a, n = torch.randn(8, spec.act_dim), torch.randn(8, spec.obs_dim)
        assert torch.equal(spec.reward_fn(x, a, n), spec.reward_fn(n, a, n)), "reward reads obs"
    base = spec.make()
    extra: dict[str, Any] = {}
    if spec.name == "halfcheetah":
        base, extra = halfcheetah_velocity_obs(base, spec.dt), HALFCHEETAH_MBRL
    env = trial_wrapper(
        gymnasium.wrappers.TimeLimit(base, args.episode_length), args.seed, args.trials, args.seed_steps
    )
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    env.action_space.seed(args.seed)  # mbrl's RandomAgent samples the action space
    cfg = mbrl_config(
        ensemble=args.ensemble,
        elites=args.ensemble,
        population=args.population,
        iterations=args.iterations,
        elite_ratio=args.elite_ratio,
        alpha=args.alpha,
        horizon=args.horizon,
        particles=args.particles,
        lr=args.lr,
        batch_size=args.batch_size,
        epochs=args.epochs,
        patience=args.patience,
        validation_ratio=args.holdout,
        weight_decay=LEARN_ENVS[spec.name]["weight_decay"],
        trial_length=args.episode_length,
        freq_train_model=args.episode_length,
        initial_exploration_steps=args.seed_steps,
        # one step more than the trials can take: the loop always reaches the reset that raises TrialsDone
        num_steps=args.trials * args.episode_length + 1,
        seed=args.seed,
        **extra,
    )
    with tempfile.TemporaryDirectory() as work_dir:
        try:
            mbrl.algorithms.pets.train(env, term_fn, reward_fn, cfg, silent=True, work_dir=work_dir)
        except TrialsDone:
            pass
        else:
            raise SystemExit(f"{PROG}: mbrl's loop ended before {args.trials} trials")
    Path(args.json).write_text(json.dumps(env.episodes))
    return 0


def _child(cmd: list[str], log: Path) -> tuple[float, float]:
    """Run ``cmd`` to the end; (wall seconds, CPU seconds user + system from the kernel's rusage)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, env=_child_env()).returncode
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if rc != 0:
        raise SystemExit(f"{PROG}: {' '.join(cmd[:4])} ... failed (exit {rc}); see {log}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _child_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _mbrl_trials(
    env: str, seed: int, trials: int, settings: dict[str, Any], work: Path
) -> tuple[float, float, list[dict[str, Any]]]:
    """One mbrl-lib run in a child process: its wall and CPU seconds and one row per trial."""
    out = work / f"mbrl-s{seed}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "_mbrl-run", "--env", env, "--seed", str(seed)]
    wall, cpu = _child([*cmd, "--json", str(out), *_setting_flags(settings)], work / f"mbrl-s{seed}.log")
    eps = [e for e in json.loads(out.read_text()) if e["phase"] == "trial"]
    keys = {"episode_reward": "reward", "episode_length": "length", "trial_wall_s": "wall_s", "trial_cpu_s": "cpu_s"}
    return wall, cpu, [{**{k: e[v] for k, v in keys.items()}, "env_steps": e["env_steps"]} for e in eps]


def _project_trials(
    env: str, seed: int, trials: int, settings: dict[str, Any], work: Path
) -> tuple[float, float, list[dict[str, Any]]]:
    """One run of this project's run_pets.py (delta, the fast preset) in a child process, as :func:`_mbrl_trials`."""
    run_dir = work / f"gem-pets-s{seed}"
    cmd = [sys.executable, str(ROOT / "run_pets.py"), "--env", env, "--model", "delta", "--preset", "fast"]
    cmd += ["--seed", str(seed), "--trials", str(trials), "--out", str(run_dir), "--quiet"]
    if run_dir.exists():
        raise SystemExit(f"{PROG}: {run_dir} exists; give a fresh --work-dir")
    wall, cpu = _child([*cmd, *_project_overrides(settings)], work / f"gem-pets-s{seed}.log")
    with open(run_dir / "metrics.csv", newline="") as f:
        metrics = list(csv.DictReader(f))
    prev = 0.0
    trial_rows = []
    for r in metrics:
        cum = float(r["wall_time_s"])
        trial_rows.append(
            {
                "episode_reward": float(r["episode_reward"]),
                "episode_length": int(r["episode_length"]),
                "trial_wall_s": cum - prev,
                "trial_cpu_s": "",
                "env_steps": int(r["env_steps"]),
            }
        )
        prev = cum
    return wall, cpu, trial_rows


def learn(args: argparse.Namespace) -> int:
    require_mbrl()
    import torch

    import envs
    from pets.experiments.studies.online import THRESHOLDS, time_to_threshold

    torch.set_num_threads(args.threads)
    spec = envs.get(args.env)
    if spec.name not in LEARN_ENVS:
        raise SystemExit(f"{PROG}: learn knows {', '.join(LEARN_ENVS)}, not {args.env}")
    threshold = float(args.episode_length) if spec.name == "invertedpendulum" else THRESHOLDS[spec.name]
    work = Path(args.work_dir) / spec.name
    work.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    mach = machine()
    print(f"{_utc_now()}: {mach}", flush=True)
    settings = learn_settings(args)
    rows: list[dict[str, Any]] = []
    for i, seed in enumerate(seeds):
        order = ("mbrl-lib", "gem-pets") if i % 2 == 0 else ("gem-pets", "mbrl-lib")
        for impl in (o for o in order if args.arms == "both" or o == args.arms):
            run = _mbrl_trials if impl == "mbrl-lib" else _project_trials
            wall, cpu, trial_rows = run(spec.name, seed, args.trials, settings, work)
            run_rows = [
                {**r, "wall_time_s": sum(t["trial_wall_s"] for t in trial_rows[: j + 1])}
                for j, r in enumerate(trial_rows)
            ]
            steps = time_to_threshold(run_rows, threshold)["steps_to_threshold"]
            print(
                f"seed {seed} {impl}: rewards {[round(r['episode_reward'], 1) for r in trial_rows]}, "
                f"wall {wall:.0f} s, cpu {cpu:.0f} s",
                flush=True,
            )
            for j, r in enumerate(trial_rows):
                rows.append(
                    {
                        "env": spec.gym_id,
                        "impl": impl,
                        "seed": seed,
                        "trial": j,
                        **r,
                        "run_wall_s": round(wall, 2),
                        "run_cpu_s": round(cpu, 2),
                        "steps_to_threshold": steps,
                        "threshold": threshold,
                    }
                )
    mach_end = machine()
    date = _utc_now()
    command = (
        f"{Path(sys.executable).parent.parent.name}/bin/python docs/scripts/{PROG} learn --env {spec.name} "
        f"--seeds {args.seeds} "
        + ("" if args.arms == "both" else f"--arms {args.arms} ")
        + " ".join(_setting_flags(settings))
    )
    for r in rows:
        r.update(
            {
                "date_utc": date,
                "cpu": mach["cpu"],
                "cpu_family_model": mach["cpu_family_model"],
                "threads": args.threads,
                "load_1min_start": mach["load_1min"],
                "load_1min_end": mach_end["load_1min"],
                "command": command,
            }
        )
    out = Path(args.out or RESULTS / f"peer_learning_{spec.name}.csv")
    write_csv(out, rows)
    if args.arms == "both":  # the paired summary needs both arms
        summary = learning_summary(rows, args.trials)
        write_csv(out.with_name(out.stem + "_summary.csv"), summary)
        for s in summary:
            print(s)
    print(f"wrote {out}")
    return 0


def _setting_flags(settings: dict[str, Any]) -> list[str]:
    return [f"--{k.replace('_', '-')}={v}" for k, v in settings.items()]


def _project_overrides(s: dict[str, Any]) -> list[str]:
    """``run_pets.py`` key=value overrides for the matched settings (CEM, TS-inf, no tensorboard)."""
    return [
        f"episode_length={s['episode_length']}",
        f"seed_steps={s['seed_steps']}",
        f"threads={s['threads']}",
        "tensorboard=false",
        "planner.name=cem",
        "planner.propagation=tsinf",
        f"planner.population={s['population']}",
        f"planner.iterations={s['iterations']}",
        f"planner.elites={s['elite_ratio']}",
        f"planner.alpha={s['alpha']}",
        f"planner.horizon={s['horizon']}",
        f"planner.particles={s['particles']}",
        f"model.ensemble_size={s['ensemble']}",
        f"model.num_elites={s['ensemble']}",
        f"model.max_epochs={s['epochs']}",
        f"model.patience={s['patience']}",
        f"model.batch_size={s['batch_size']}",
        f"model.lr={s['lr']}",
        f"model.holdout_ratio={s['holdout']}",
    ]


def learning_summary(rows: list[dict[str, Any]], trials: int) -> list[dict[str, Any]]:
    """Per metric: each arm's mean, and the paired difference gem-pets - mbrl-lib over the seeds both have, its
    mean, 95 % percentile-bootstrap CI (pets.stats.bootstrap.bootstrap_ci) and the exact sign-flip
    p-value (sign_flip_p). Metrics: final reward (mean of the last 3 trials), mean reward over all trials, env
    steps taken (seed phase included), reached the threshold (1/0), env steps to the threshold (seeds where both
    reached it), wall seconds per trial (all trials), CPU seconds per trial and per env step (the run's CPU from
    rusage, process start-up and seed phase included, / trials or / env steps), the run's CPU seconds."""
    import numpy as np

    from pets.experiments.statistics import paired_differences, sign_flip_p
    from pets.stats.bootstrap import bootstrap_ci

    per: dict[str, dict[str, dict[int, float]]] = {}
    for impl in ("gem-pets", "mbrl-lib"):
        runs: dict[int, list[dict[str, Any]]] = {}
        for r in rows:
            if r["impl"] == impl:
                runs.setdefault(r["seed"], []).append(r)
        m = per.setdefault(impl, {})
        for seed, rs in runs.items():
            rewards = [float(r["episode_reward"]) for r in rs]
            m.setdefault("final_reward_last3", {})[seed] = float(np.mean(rewards[-3:]))
            m.setdefault("mean_reward_all_trials", {})[seed] = float(np.mean(rewards))
            m.setdefault("trials_run", {})[seed] = float(len(rs))
            steps = float(rs[-1]["env_steps"])
            m.setdefault("env_steps", {})[seed] = steps
            to_threshold = float(rs[0]["steps_to_threshold"])
            m.setdefault("reached_threshold", {})[seed] = float(math.isfinite(to_threshold))
            if math.isfinite(to_threshold):
                m.setdefault("steps_to_threshold", {})[seed] = to_threshold
            m.setdefault("wall_s_per_trial", {})[seed] = float(np.mean([float(r["trial_wall_s"]) for r in rs]))
            m.setdefault("cpu_s_per_trial", {})[seed] = float(rs[0]["run_cpu_s"]) / len(rs)
            m.setdefault("cpu_s_per_env_step", {})[seed] = float(rs[0]["run_cpu_s"]) / steps
            m.setdefault("run_cpu_s", {})[seed] = float(rs[0]["run_cpu_s"])
    out = []
    for metric in dict.fromkeys([*per["gem-pets"], *per["mbrl-lib"]]):
        a, b = per["gem-pets"].get(metric, {}), per["mbrl-lib"].get(metric, {})
        seeds, d = paired_differences(a, b)
        d = d[:, 0] if d.size else d
        low, high = bootstrap_ci(d) if len(seeds) else (float("nan"), float("nan"))
        out.append(
            {
                "metric": metric,
                "n_pairs": len(seeds),
                "gem_pets_mean": float(np.mean([a[s] for s in seeds])) if seeds else float("nan"),
                "mbrl_lib_mean": float(np.mean([b[s] for s in seeds])) if seeds else float("nan"),
                "diff_mean": float(d.mean()) if len(seeds) else float("nan"),
                "diff_ci_low": low,
                "diff_ci_high": high,
                "sign_flip_p": sign_flip_p(d) if len(seeds) else float("nan"),
            }
        )
    return out


def summarise(args: argparse.Namespace) -> int:
    """The summary CSV of a ``learn`` runs CSV again (no mbrl-lib needed)."""
    path = Path(args.runs)
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    trials = max(int(r["trial"]) for r in rows) + 1
    summary = learning_summary(rows, trials)
    write_csv(path.with_name(path.stem + "_summary.csv"), summary)
    for row in summary:
        print(row)
    return 0


# ---------------------------------------------------------------------------------------------- setup
def setup(args: argparse.Namespace) -> int:
    venv = Path(args.venv)
    py = venv / "bin" / "python"
    if not py.exists():
        subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    subprocess.run([str(py), "-m", "pip", "install", "--no-deps", *PINS], check=True)
    print(f"mbrl-lib installed: run {py} docs/scripts/{PROG} plan (from {ROOT})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    s = sub.add_parser("setup", help="make a venv with mbrl-lib (no-deps pins) that sees this interpreter's packages")
    s.add_argument("venv")
    s = sub.add_parser("plan", help="time the HalfCheetah research planning step, mbrl-lib vs this project")
    s.add_argument("--repeats", type=int, default=7, help="rounds (steps per row); medians over them")
    s.add_argument("--threads", type=int, default=1, help="torch intra- and inter-op threads")
    s.add_argument("--out", default=str(RESULTS / "peer_planning_step.csv"))
    s = sub.add_parser("summarise", help="write RUNS_summary.csv again from a learn runs CSV")
    s.add_argument("runs")
    s = sub.add_parser("profile", help="torch.profiler over one mbrl-lib planning step at the plan shapes")
    s.add_argument("--threads", type=int, default=1)
    s.add_argument("--repeats", type=int, default=3, help="timed steps per allocator setting")
    s.add_argument("--rows", type=int, default=15)
    for name, helptext in (
        ("learn", "mbrl-lib's PETS loop vs run_pets.py --model delta, paired seeds"),
        ("_mbrl-run", argparse.SUPPRESS),
    ):
        s = sub.add_parser(name, help=helptext)
        s.add_argument("--env", required=True, choices=tuple(LEARN_ENVS))
        s.add_argument("--trials", type=int, default=5)
        s.add_argument("--episode-length", type=int, default=100)
        s.add_argument("--seed-steps", type=int, default=200)
        s.add_argument("--ensemble", type=int, default=5, help="members, all propagated (elites = members)")
        s.add_argument("--population", type=int, default=100)
        s.add_argument("--iterations", type=int, default=3)
        s.add_argument("--elite-ratio", type=float, default=0.1)
        s.add_argument("--alpha", type=float, default=0.1)
        s.add_argument("--horizon", type=int, default=20)
        s.add_argument("--particles", type=int, default=5)
        s.add_argument("--epochs", type=int, default=50)
        s.add_argument("--patience", type=int, default=5)
        s.add_argument("--batch-size", type=int, default=32)
        s.add_argument("--lr", type=float, default=1e-3)
        s.add_argument("--holdout", type=float, default=0.1)
        s.add_argument("--threads", type=int, default=1)
        if name == "learn":
            s.add_argument("--seeds", default="0,1,2,3,4")
            s.add_argument("--work-dir", default="/tmp/peer-mbrl")
            s.add_argument("--out", help="default docs/results/peer_learning_ENV.csv (+ _summary.csv)")
            s.add_argument(
                "--arms",
                choices=("both", "mbrl-lib"),
                default="both",
                help="mbrl-lib: its runs alone, beside this project's runs made elsewhere (no summary)",
            )
        else:
            s.add_argument("--seed", type=int, required=True)
            s.add_argument("--json", required=True)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "setup":
            return setup(args)
        if args.command == "summarise":
            return summarise(args)
        return {"plan": plan, "profile": profile, "learn": learn, "_mbrl-run": mbrl_run}[args.command](args)
    except MbrlMissing as err:
        print(f"{PROG}: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
