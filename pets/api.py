"""The Python API: PETS with a swappable dynamics model, as an object (docs/api.md).

A thin layer over what ``run_pets.py`` runs: :class:`PETS` holds one :class:`pets.loop.PETSRun` (the config,
the model, the trainer, the MPC agent, the replay buffer and every random state), and ``save`` writes the same
run directory as ``run_pets.py`` (``config.yaml``, ``checkpoint.pt``, ``metrics.csv``), so either side can
continue what the other started: ``PETS.load(DIR)`` or ``run_pets.py --resume DIR``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from dynamics.model import DynamicsModel

if TYPE_CHECKING:
    from pets.loop import PETSRun

__all__ = ["PETS", "load_model"]


class PETS:
    """PETS (probabilistic ensemble, trajectory sampling, CEM/iCEM/MPPI with MPC) on a catalogue env.

    env: a catalogue name or gymnasium id (``"halfcheetah"``, ``"Ant-v5"``).
    model: a ``--model`` name (``delta``, ``gem``, ``gem-se``, ...; docs/models.md).
    preset: ``research`` (the PETS papers' planner) or ``fast`` (~20x cheaper per step, for CPUs).
    seed: fixes every random source (two runs with the same seed on one machine give the same metrics).
    device: ``auto``, ``cpu`` or ``cuda``.
    overrides: any config key (``pets/config.py``), e.g. ``seed_steps=500``; dotted keys as
      ``**{"planner.horizon": 10}``. A bad key or value raises ``pets.config.ConfigError`` naming it.
      ``imports=["my_planner"]``: modules imported first (your own planners, models, codecs; :mod:`pets.imports`),
      recorded in the run so that ``PETS.load`` of it imports them again.
    progress: tqdm bars while learning.
    """

    def __init__(
        self,
        env: str,
        model: str = "gem",
        preset: str = "research",
        *,
        seed: int = 0,
        device: str = "auto",
        progress: bool = False,
        **overrides: Any,
    ) -> None:
        import envs
        from pets.config import ConfigError, make_config
        from pets.imports import import_modules

        overrides["imports"] = import_modules(plain_value(overrides.get("imports", [])))  # before the env: its codecs
        try:
            name = envs.get(env).name
        except ValueError as err:
            raise ConfigError(str(err)) from None
        settings = {"seed": seed, "device": device, **overrides}
        cfg = make_config(name, model, preset, {key: plain_value(value) for key, value in settings.items()})
        self._start(cfg, progress)

    def _start(self, cfg: Any, progress: bool) -> None:
        from pets.builder import resolve_device
        from pets.loop import PETSRun

        resolve_device(cfg.device)
        self._run = PETSRun(cfg)
        self.progress = progress
        #: The planner's random state of :meth:`act`, apart from learning's (``plan_gen``): acting leaves it as is.
        self._act_state = torch.Generator(device=self._run.device).manual_seed(cfg.seed + 5).get_state()
        #: The run directories this object was loaded from or saved to: ``save`` may write there again.
        self._dirs: set[Path] = set()

    # ------------------------------------------------------------------ what it holds
    @property
    def config(self) -> Any:
        """The resolved config (an omegaconf ``DictConfig``; read-only by convention)."""
        return self._run.cfg

    @property
    def model(self) -> DynamicsModel:
        """The dynamics model (head + ensemble + normalisers), trained on all data after every trial."""
        return self._run.model

    @property
    def history(self) -> list[dict[str, Any]]:
        """One row per trial, the columns of ``metrics.csv`` (episode reward, env steps, losses, timings)."""
        return list(self._run.rows)

    @property
    def trials_done(self) -> int:
        return self._run.trials_done

    # ------------------------------------------------------------------ learning and acting
    def learn(self, trials: int | None = None, callback: Callable[[dict[str, Any]], Any] | None = None) -> PETS:
        """Run ``trials`` more trials (default: up to the config's ``trials``), each one real episode with the MPC
        agent followed by training on all data; the first is preceded by ``seed_steps`` random steps. Fewer where
        the run is done first, as ``run_pets.py`` stops: its env-step budget ``max_env_steps`` spent (``--preset
        locomotion``) or a trial at ``stop_reward``. ``callback(row)`` gets every trial's row; returning ``False``
        stops. A trial that Ctrl-C or an error stops is undone (``learn`` again replays it). Returns ``self``."""
        if isinstance(trials, np.integer):
            trials = int(trials)
        if trials is not None and (isinstance(trials, bool) or not isinstance(trials, int) or trials < 1):
            raise ValueError(f"trials must be a positive int or None, got {trials!r}")
        if callback is not None and not callable(callback):
            raise ValueError(f"callback must be a function of a trial's row (or None), got {type(callback).__name__}")
        from pets.runs.rundir import stopped

        run, cfg = self._run, self.config
        target = cfg.trials if trials is None else run.trials_done + trials
        while run.trials_done < target and not stopped(run.rows, cfg.stop_reward, cfg.max_env_steps):
            before = _snapshot(run)
            try:
                row = run.run_trial(progress=self.progress)
            except BaseException:  # Ctrl-C or a failure: the trial is undone; learning again replays it from its start
                run.load_state_dict(before)
                raise
            if callback is not None and callback(dict(row)) is False:
                break
        return self

    def act(self, obs: Any) -> np.ndarray:
        """One MPC step: the first action (act_dim,) of a plan from one observation ``obs`` (obs_dim,) (numpy, a list
        or a torch tensor), warm-started from the last plan. Call :meth:`reset` at the start of every new episode.
        Its random draws are a stream of its own (from ``seed``): acting between ``learn`` calls leaves what they learn
        as it was. ValueError (one line) for anything but one finite observation."""
        x = self._observation(obs)
        gen = self._run.plan_gen
        learning = gen.get_state()
        gen.set_state(self._act_state)
        try:
            return self._run.agent.act(x)
        finally:
            self._act_state = gen.get_state()
            gen.set_state(learning)

    def _observation(self, obs: Any) -> np.ndarray:
        """``obs`` as one float32 observation (obs_dim,); ValueError (one line) naming what is wrong with it."""
        if isinstance(obs, tuple) and len(obs) == 2 and isinstance(obs[1], dict):
            raise ValueError("act takes the observation, not reset()'s (obs, info) pair: obs, _ = env.reset()")
        if isinstance(obs, torch.Tensor):
            obs = obs.detach().cpu()
        try:
            x = np.asarray(obs)
        except (TypeError, ValueError):  # a ragged list
            x = np.asarray(None)
        if x.dtype.kind not in "biuf":  # None, strings, objects, complex numbers
            raise ValueError(f"obs must be an array of numbers, got {type(obs).__name__} {obs!r:.60}")
        want = (self._run.spec.obs_dim,)
        if x.shape != want:
            batch = " (act takes one observation, not a batch)" if x.ndim > 1 and x.shape[-1:] == want else ""
            raise ValueError(f"obs must have shape {want}, the env's observation, got {x.shape}{batch}")
        x = x.astype(np.float32)
        if not np.isfinite(x).all():
            raise ValueError(f"obs holds nan or inf at entries {np.flatnonzero(~np.isfinite(x)).tolist()}")
        return x

    def reset(self) -> None:
        """Forget the warm start (a new episode)."""
        self._run.agent.reset()

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> Path:
        """Write the run directory (config.yaml, checkpoint.pt, metrics.csv) to ``path``; returns it.

        As ``run_pets.py``, it never writes over another run: ``path`` must be new (or hold no run), or the directory
        this object was loaded from or saved to before. ConfigError (one line) for a directory that holds another
        run; ``DirectoryInUse`` while a command runs in it (its lock is taken for the write)."""
        import pets.runs.rundir as rundir
        from pets.config import ConfigError
        from pets.runs.fileio import DirectoryInUse, locked, new_run_dir_error

        path = _directory(path, "PETS.save")
        if path.exists() and not path.is_dir():
            raise ConfigError(f"{path} is a file; save to a directory (new, or this run's own)")
        run_files = any((path / f).exists() for f in (rundir.CONFIG_FILE, rundir.CHECKPOINT_FILE))
        if not run_files and (problem := new_run_dir_error(path, "save to a new directory")):
            raise ConfigError(problem)  # a folder of other files: a run's files would be written over or among them
        try:
            with locked(path):
                ours = path.resolve() in self._dirs
                if not ours and any((path / f).exists() for f in (rundir.CONFIG_FILE, rundir.CHECKPOINT_FILE)):
                    raise ConfigError(
                        f"{path} already holds a run; save to another directory, or continue that run with "
                        f"pets.PETS.load({str(path)!r})"
                    )
                if rundir.recorded_trials(path) > self.trials_done:  # resumed elsewhere since: newer than this
                    raise ConfigError(
                        f"{path} has gone on to {rundir.recorded_trials(path)} trials since this object saved or "
                        f"loaded it ({self.trials_done}); save to another directory, or load it again"
                    )
                rundir.write_config(path, self.config)
                rundir.save_checkpoint(path, self._run.state_dict())
                rundir.write_metrics(path, self._run.rows)
        except DirectoryInUse as err:
            raise DirectoryInUse(
                f"{err}; nothing was saved: save to another directory, or when it has finished"
            ) from None
        self._dirs.add(path.resolve())
        return path

    @classmethod
    def load(cls, path: str | Path, progress: bool = False) -> PETS:
        """A PETS object from a run directory (``save``'s or ``run_pets.py``'s): config, model, buffer and random
        states, so that ``learn`` continues exactly where the run stopped."""
        import pets.runs.rundir as rundir
        from pets.config import ConfigError, load_run_config

        path = _directory(path, "PETS.load")
        cfg = load_run_config(path)
        obj = cls.__new__(cls)
        obj._start(cfg, progress)
        state = rundir.load_checkpoint(path)
        if state is not None:
            if "offline" in state:
                raise ConfigError(f"{path} is an offline training run (pets.train); use pets.load_model for its model")
            rundir.check_resumed_config(path, state, cfg)
            try:
                obj._run.load_state_dict(state)
            except (KeyError, TypeError) as err:  # a readable file that is not a whole run's state
                raise ConfigError(
                    f"{path / rundir.CHECKPOINT_FILE} is not a complete run checkpoint (missing {err}); "
                    "restore it from a copy"
                ) from None
            rundir.check_finite_buffer(path, obj._run.buffer.state_dict())  # as run_pets.py --resume refuses it
        elif rundir.recorded_trials(path):
            raise ConfigError(rundir.missing_checkpoint_message(path))
        obj._dirs.add(path.resolve())
        return obj

    def __repr__(self) -> str:
        c = self.config
        return f"PETS(env={c.env!r}, model={c.head!r}, trials_done={self.trials_done}, seed={c.seed})"


def _snapshot(run: PETSRun) -> dict[str, Any]:
    """``run.state_dict()`` as it is now, to restore after an interrupted trial: copies, but for the replay buffer's
    arrays, which a trial replaces and never writes into."""
    state = run.state_dict()
    buffer = state.pop("buffer")
    return {**copy.deepcopy(state), "buffer": dict(buffer)}


def plain_value(value: Any) -> Any:
    """``value`` with numpy scalars and arrays as the Python numbers and lists they hold (``np.int64(50)`` is 50,
    as computed settings often are); anything else unchanged (the config checks its type)."""
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    if isinstance(value, list | tuple):
        return [plain_value(v) for v in value]
    return value


def load_model(path: str | Path, device: str = "cpu") -> DynamicsModel:
    """The trained dynamics model of a run directory (online or offline), in eval mode:
    ``model.predict(obs, act)`` and ``model.rollout(obs, actions)`` take numpy arrays or tensors."""
    from pets.builder import load_model as load

    return load(_directory(path, "pets.load_model"), device)[2]


def _directory(path: Any, caller: str) -> Path:
    """``path`` as a Path: TypeError (one line) for what is not a path, ConfigError for an empty one (it would be the
    working directory)."""
    import os

    from pets.config import ConfigError

    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"{caller} takes a run directory (str or pathlib.Path), got {type(path).__name__} {path!r}")
    if not os.fspath(path):
        raise ConfigError(f"{caller} got an empty path; name the run directory")
    return Path(path)
