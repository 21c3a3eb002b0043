"""The model-based RL loop: random seed steps, then alternate model training and MPC trials.

After every completed trial the run directory gets its video (``video_every``) and TensorBoard scalars
(:mod:`pets.runs.tblog`), an atomic checkpoint (model, optimiser, normaliser, replay buffer, all RNG states,
metrics so far), then metrics.csv and rewards.png.
``run(..., resume=True)`` continues from the last checkpoint; an interrupted trial is replayed
from its start with the RNG states it began with, so a resumed run matches an uninterrupted one.
``history.csv`` gets a row per session (start or resume, with the trials done when it began).
"""

from __future__ import annotations

import itertools
import math
import random
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

import envs
from pets import builder
from pets.config import ConfigError
from pets.data.buffer import ReplayBuffer
from pets.data.rollout import EnvFailed, Episode, MPCPolicy, RandomPolicy, run_episode, run_steps
from pets.learning.trainer import TrainingDiverged, TrainResult
from pets.models import make_model
from pets.planning.cost import CostEstimate, compile_line
from pets.planning.planners import PlanningFailed
from pets.planning.value import episode_ends, returns_to_go
from pets.runs import rundir
from pets.runs.fileio import locked, new_run_dir_error
from pets.runs.tblog import ScalarLog
from pets.runs.video import EpisodeRecorder, trial_video_path

#: Episode indices of the random seed phase start here (the trials' episodes are 0, 1, ...).
SEED_PHASE = 50_000


def episode_reset_seed(seed: int, index: int) -> int:
    """The env reset seed of episode ``index`` of a run with ``seed`` (seed-phase episodes from :data:`SEED_PHASE`)."""
    return seed * 100_003 + index


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


class Stateful(Protocol):
    """A part of a run with a state dict (a module, the trainer, the buffer, an adapter of an RNG)."""

    def state_dict(self) -> Any: ...

    def load_state_dict(self, state: Any) -> None: ...


class Part:
    """A state-dict part made of a getter and a setter (RNG states, plain values)."""

    def __init__(self, get: Callable[[], Any], put: Callable[[Any], None]) -> None:
        self.get, self.put = get, put

    def state_dict(self) -> Any:
        return self.get()

    def load_state_dict(self, state: Any) -> None:
        self.put(state)


def generator_part(generator: torch.Generator) -> Part:
    """A torch generator's state as a part."""
    return Part(generator.get_state, generator.set_state)


class PETSRun:
    """Holds every stateful part of a run (:meth:`parts`); ``state_dict``/``load_state_dict`` cover all of it."""

    def __init__(self, cfg: DictConfig) -> None:
        self.cfg = cfg
        self.spec = envs.get(cfg.env)
        self.device = builder.resolve_device(cfg.device)
        builder.check_memory(cfg, self.spec)  # a config this machine cannot hold: one line, before any allocation
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        seed_everything(cfg.seed)
        self.env = self.spec.make()
        self.episode_length = cfg.episode_length or self.spec.episode_length
        self.model = make_model(cfg, self.spec, self.device)
        self.trainer = builder.make_trainer(cfg, self.model)
        self.train_gen = torch.Generator(device=self.device).manual_seed(cfg.seed + 1)
        self.plan_gen = torch.Generator(device=self.device).manual_seed(cfg.seed + 2)
        self.np_rng = np.random.default_rng(cfg.seed + 3)
        self.value = builder.make_value(cfg, self.spec, self.device) if cfg.value.enabled else None
        self.value_gen = torch.Generator(device=self.device).manual_seed(cfg.seed + 4)
        self.agent = builder.make_agent(cfg, self.spec, self.model, self.device, self.plan_gen, self.value)
        self.mpc_policy = MPCPolicy(self.agent)
        self.random_policy = RandomPolicy(self.spec.action_low, self.spec.action_high)
        self.buffer = ReplayBuffer(self.spec.obs_dim, self.spec.act_dim)
        self.rows: list[dict[str, Any]] = []
        self.trials_done = 0
        self.env_steps = 0
        self.wall_time_s = 0.0
        self.cpu_time_s = 0.0
        #: The current trial's process CPU seconds in model training and in the terminal value's fit.
        self.trial_cpu = {"train": 0.0, "value": 0.0}
        self.last_train: TrainResult | None = None
        self.recorder = EpisodeRecorder(self.spec, self.env) if cfg.video_every else None
        #: Set by :func:`run`: the one-line estimate of a long run from its first planning steps (pets.planning.cost).
        self.cost: CostEstimate | None = None

    # --- state -----------------------------------------------------------------------------
    #: The run's progress, kept in the checkpoint as plain values (the parts below have state dicts).
    PROGRESS = ("trials_done", "env_steps", "wall_time_s", "rows")
    #: Progress added later, with its value for a checkpoint written before it (NaN: not known).
    LATER_PROGRESS = {"cpu_time_s": math.nan}

    def parts(self) -> dict[str, Stateful]:
        """Every stateful part of the run by its checkpoint key, in loading order (the model before the trainer,
        whose optimiser holds the model's parameters); the value and the feedback law where the config has them."""
        parts: dict[str, Stateful] = {
            "model": Part(self.model.state_dict, lambda state: rundir.load_model_state(self.model, {"model": state})),
            "trainer": self.trainer,
            "buffer": self.buffer,
            "train_gen": generator_part(self.train_gen),
            "plan_gen": generator_part(self.plan_gen),
            "np_rng": Part(lambda: self.np_rng.bit_generator.state, self._set_np_rng),
            "torch_rng": Part(torch.get_rng_state, torch.set_rng_state),
            "last_train": Part(lambda: self.last_train, lambda state: setattr(self, "last_train", state)),
        }
        if self.value is not None:
            parts.update(value=self.value, value_gen=generator_part(self.value_gen))
        if self.agent.feedback is not None:
            parts["feedback"] = self.agent.feedback
        return parts

    def _set_np_rng(self, state: dict[str, Any]) -> None:
        self.np_rng.bit_generator.state = state

    def state_dict(self) -> dict[str, Any]:
        """The checkpoint: the config, the progress and every part's state dict."""
        progress = {key: getattr(self, key) for key in (*self.PROGRESS, *self.LATER_PROGRESS)}
        parts = {key: part.state_dict() for key, part in self.parts().items()}
        return {"config": OmegaConf.to_container(self.cfg), **progress, **parts}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from a checkpoint of :meth:`state_dict` (also one written before the parts had a protocol:
        the keys are the same); ConfigError for a checkpoint of an older format or a mismatched model."""
        for key in self.PROGRESS:  # a KeyError first: not a run's checkpoint at all
            setattr(self, key, state[key])
        for key, unknown in self.LATER_PROGRESS.items():
            setattr(self, key, state.get(key, unknown))
        if "model" not in state:
            rundir.load_model_state(self.model, state)  # a run's checkpoint of an older format: says so
        for key, part in self.parts().items():
            part.load_state_dict(state[key])

    def finished(self) -> bool:
        """All ``trials`` done, a trial's reward at ``stop_reward``, or the env-step budget ``max_env_steps`` spent."""
        cfg = self.cfg
        return self.trials_done >= cfg.trials or rundir.stopped(self.rows, cfg.stop_reward, cfg.max_env_steps)

    # --- one trial ---------------------------------------------------------------------------
    def _train(self, when: str | None = None) -> None:
        """Train on all data so far; TrainingDiverged names where (``when``, default: the current trial)."""
        obs, act, next_obs = self.buffer.tensors(self.device)
        start = time.process_time()
        try:
            self.last_train = self.trainer.train(obs, act, next_obs, self.train_gen)
        except TrainingDiverged as err:
            raise TrainingDiverged(f"{when or f'trial {self.trials_done}'}: {err}") from None
        self.trial_cpu["train"] += time.process_time() - start
        if self.value is not None:
            start = time.process_time()
            self._fit_value(obs, act, next_obs)
            self.trial_cpu["value"] += time.process_time() - start
        if self.agent.feedback is not None:
            self.agent.feedback.fit_scale(obs)

    def _fit_value(self, obs: torch.Tensor, act: torch.Tensor, next_obs: torch.Tensor) -> None:
        """Fit the terminal value to the discounted real returns-to-go of the buffer's episodes
        (pets.planning.value)."""
        with torch.no_grad():
            rewards = self.spec.reward(obs, act, next_obs)
            terminal = self.spec.terminated(obs, act, next_obs)
            bootstrap = torch.where(terminal, torch.zeros_like(rewards), self.value(next_obs))
        targets = returns_to_go(rewards, episode_ends(obs, next_obs), bootstrap, self.cfg.value.discount)
        self.value.fit(obs, targets, self.value_gen, steps=self.cfg.value.steps)

    def _episode_seed(self, index: int) -> int:
        return episode_reset_seed(self.cfg.seed, index)

    def _add(self, episode: Episode, start: int = 0) -> None:
        """Put the transitions ``start:`` of ``episode`` into the replay buffer."""
        self.buffer.add_episode(episode.obs[start:], episode.act[start:], episode.next_obs[start:])

    def max_steps(self) -> int:
        """The next episode's most steps: the episode length, cut at the budget ``max_env_steps`` if one is set."""
        budget = self.cfg.max_env_steps
        return self.episode_length if budget is None else min(self.episode_length, budget - self.env_steps)

    def collect_seed_data(self) -> None:
        """``seed_steps`` uniformly random steps over as many episodes as needed, then the first training."""
        seeds = (self._episode_seed(SEED_PHASE + i) for i in itertools.count())
        try:
            episodes = run_steps(
                self.env,
                self.random_policy,
                self.cfg.seed_steps,
                max_steps=self.episode_length,
                reset_seeds=seeds,
                rng=self.np_rng,
            )
        except EnvFailed as err:
            raise EnvFailed(f"the random steps before trial 0 (seed_steps): {err}") from None
        for episode in episodes:
            self._add(episode)
            self.env_steps += len(episode)
        if episodes:
            self._train(when="training on the seed data before trial 0")

    def run_trial(self, progress: bool = True) -> dict[str, Any]:
        """Collect one episode with the MPC agent, then train the model on all data so far."""
        trial, start, start_cpu = self.trials_done, time.perf_counter(), time.process_time()
        self.trial_cpu = {"train": 0.0, "value": 0.0}
        if trial == 0 and len(self.buffer) == 0:
            self.collect_seed_data()
        random_policy = len(self.buffer) == 0  # seed_steps=0: the first trial explores at random
        if self.recorder is not None and trial % self.cfg.video_every == 0:
            self.recorder.start()  # frames after every step; the caller saves them (before the checkpoint)
        policy = self.random_policy if random_policy else self.mpc_policy
        bar = tqdm(total=self.episode_length, desc=f"trial {trial}", leave=False, disable=not progress)
        added = 0  # steps of this episode already in the buffer
        steps = 0  # steps of this episode taken

        def after_step(so_far: Episode) -> None:
            """Progress bar; with ``train_every``, mid-episode training on the data so far."""
            nonlocal added, steps
            steps = len(so_far)
            if self.recorder is not None:
                self.recorder.capture()
            bar.update(1)
            bar.set_postfix(reward=f"{so_far.total_reward:.1f}")
            if self.cost is not None and not random_policy:
                line = self.cost.step(steps, self.mpc_policy.seconds)
                if line:
                    tqdm.write(line, file=sys.stderr)
            every, after_trial = self.cfg.train_every, self.cfg.train_after_trial
            due = every and (self.env_steps + len(so_far)) % every == 0
            if due and not random_policy and not (so_far.done and after_trial):  # after a trial: trained below
                self._add(so_far, added)
                added = len(so_far)
                self._train()

        try:
            episode = run_episode(
                self.env,
                policy,
                max_steps=self.max_steps(),
                reset_seed=self._episode_seed(trial),
                rng=self.np_rng,
                on_step=after_step,
            )
        except PlanningFailed as err:  # name where it happened; the trials before it are checkpointed
            raise PlanningFailed(f"trial {trial}, step {steps}: {err}") from None
        except EnvFailed as err:  # the env's own step names itself
            raise EnvFailed(f"trial {trial}: {err}") from None
        finally:
            bar.close()
        self._add(episode, added)
        length = len(episode)
        if self.cfg.train_after_trial or random_policy:
            self._train()
        self.env_steps += length
        self.trials_done += 1
        self.wall_time_s += time.perf_counter() - start
        self.cpu_time_s += time.process_time() - start_cpu
        lt = self.last_train
        row = {
            "trial": trial,
            "env_steps": self.env_steps,
            "episode_reward": episode.total_reward,
            "episode_length": length,
            "terminated": int(bool(episode.terminated[-1])),
            "model_train_loss": lt.train_loss,
            "model_val_loss": lt.val_loss,
            "model_val_loss_initial": lt.initial_val_loss,
            "model_epochs": lt.epochs,
            "plan_seconds_per_step": 0.0 if random_policy else self.mpc_policy.seconds / length,
            "plan_cpu_s": 0.0 if random_policy else round(self.mpc_policy.cpu_seconds, 3),
            "train_cpu_s": round(self.trial_cpu["train"], 3),
            "value_cpu_s": round(self.trial_cpu["value"], 3),
            "wall_time_s": round(self.wall_time_s, 3),
            "cpu_time_s": round(self.cpu_time_s, 3),
        }
        self.rows.append(row)
        return row


def _run_bar(cfg: DictConfig, pets_run: PETSRun, progress: bool) -> tqdm:
    """The run's progress bar: its trials, or its env steps where an env-step budget ends it (its ``trials`` are
    then an upper bound, e.g. ``--preset locomotion``'s 100,000)."""
    if cfg.max_env_steps is None:
        total, initial, unit = cfg.trials, pets_run.trials_done, "trial"
    else:
        total, initial, unit = cfg.max_env_steps, min(pets_run.env_steps, cfg.max_env_steps), "step"
    desc = f"{envs.file_name(cfg.env)}-{cfg.head}"  # your own env by its spec's name, not its import path
    return tqdm(total=total, initial=initial, desc=desc, unit=unit, disable=not progress)


def run(cfg: DictConfig, run_dir: Path, resume: bool = False, progress: bool = True) -> list[dict[str, Any]]:
    """Run (or continue) the PETS loop in ``run_dir`` until ``cfg.trials`` trials are done, a trial's reward
    reaches ``cfg.stop_reward`` or the env-step budget ``cfg.max_env_steps`` is spent (:meth:`PETSRun.finished`).
    A new run needs a new or empty ``run_dir`` (ConfigError for one that holds other files: they would be written over
    or mixed with the run's)."""
    if not resume and not (run_dir / rundir.CONFIG_FILE).exists() and (problem := new_run_dir_error(run_dir)):
        raise ConfigError(problem)
    with locked(run_dir):  # one process per run directory; DirectoryInUse for a second one
        if not resume and (run_dir / rundir.CONFIG_FILE).exists():
            raise ConfigError(
                f"{run_dir} already holds a run; continue it with --resume {run_dir} or pick another --out"
            )
        return _run_locked(cfg, run_dir, resume, progress)


def _run_locked(cfg: DictConfig, run_dir: Path, resume: bool, progress: bool) -> list[dict[str, Any]]:
    pets_run = PETSRun(cfg)
    title = f"{cfg.env} / {cfg.head} / seed {cfg.seed}"
    if resume:
        state = rundir.load_checkpoint(run_dir)
        if state is not None and "offline" in state:
            raise ConfigError(f"{run_dir} is an offline training run (pets.train); it cannot be resumed online")
        if state is not None:
            rundir.check_resumed_config(run_dir, state, cfg)
            try:
                pets_run.load_state_dict(state)
            except (KeyError, TypeError) as err:  # a readable file that is not a whole run's state
                raise ConfigError(
                    f"{run_dir / rundir.CHECKPOINT_FILE} is not a complete run checkpoint (missing {err}); "
                    "restore it from a copy, or delete it to start the run over"
                ) from None
            rundir.check_finite_buffer(run_dir, pets_run.buffer.state_dict())
        elif rundir.recorded_trials(run_dir):
            raise ConfigError(rundir.missing_checkpoint_message(run_dir))
        rundir.write_metrics(run_dir, pets_run.rows)  # the checkpoint is the source of truth for the rows
        if pets_run.rows:  # a run killed right after its checkpoint, or resumed when finished, gets its plot
            rundir.plot_rewards(run_dir, pets_run.rows, title)
    else:
        rundir.write_config(run_dir, cfg)
    rundir.append_history(run_dir, "resume" if resume else "start", pets_run.trials_done)
    rundir.record_divergence(run_dir, None)  # a resumed run tries again
    budget_left = None if cfg.max_env_steps is None else cfg.max_env_steps - pets_run.env_steps
    pets_run.cost = CostEstimate(cfg, pets_run.episode_length, cfg.trials - pets_run.trials_done, budget_left)
    if not pets_run.finished() and (line := compile_line(cfg)):  # none when nothing is left (budget spent)
        tqdm.write(line, file=sys.stderr)
    # Events past the last checkpoint (an interrupted trial's) are purged; each trial is written before its
    # checkpoint, so a resumed run neither loses nor repeats a scalar (pets.runs.tblog).
    events = ScalarLog(run_dir, cfg.tensorboard, purge_step=pets_run.env_steps + 1 if resume else None)
    bar = _run_bar(cfg, pets_run, progress)
    try:
        while not pets_run.finished():
            row = pets_run.run_trial(progress=progress)
            if pets_run.recorder is not None and pets_run.recorder.recording:
                pets_run.recorder.save(trial_video_path(run_dir, int(row["trial"])))
            events.trial(row)
            rundir.save_checkpoint(run_dir, pets_run.state_dict())
            rundir.write_metrics(run_dir, pets_run.rows)
            rundir.plot_rewards(run_dir, pets_run.rows, title)
            bar.update(1 if cfg.max_env_steps is None else pets_run.env_steps - bar.n)
            bar.set_postfix(reward=f"{row['episode_reward']:.1f}", steps=row["env_steps"])
    except (TrainingDiverged, PlanningFailed) as err:  # an outcome of the run: a comparison counts it as the worst
        rundir.record_divergence(run_dir, str(err))
        raise
    finally:
        events.close()
        if pets_run.recorder is not None:
            pets_run.recorder.close()
    bar.close()
    pets_run.env.close()
    return pets_run.rows
