"""Offline training of a dynamics model on a collected data set, into a run directory.

The command ``python -m pets.train`` is :mod:`pets.tools.train`.

MODEL is any ``--model`` of ``run_pets.py`` (``pets.config.HEADS``: delta, gem, delta-det, gem2,
delta-groupfeat; :mod:`pets.models` describes each). The deterministic ones (delta-det, gem2) train by MSE /
the Frobenius loss; the paper's single model is ``model.ensemble_size=1 model.num_elites=1``, its averaged
ensemble ``model.ensemble_size=5 model.num_elites=5``.

The run directory has the format of ``run_pets.py`` (:mod:`pets.runs.rundir`), so
``pets.builder.load_model``, ``pets.evaluate`` and ``pets.collect --policy run:DIR`` read it:

- ``config.yaml``: the resolved config (env from the data set, ``head`` = MODEL, overrides applied);
- ``checkpoint.pt``: ``model`` and ``trainer`` (optimiser) state, ``trials_done`` = 0,
  ``env_steps`` = 0, ``wall_time_s``, ``rows``, ``last_train`` (the ``TrainResult``) and ``offline``
  (data file, episodes, transitions, the data set's policy and seed);
- ``metrics.csv``: one row with ``model_train_loss``, ``model_val_loss``, ``model_val_loss_initial``, ``model_epochs``,
  ``wall_time_s``, ``cpu_time_s`` and ``env_steps`` (= transitions trained on); NaN in the other columns;
- TensorBoard events (config key ``tensorboard``, :mod:`pets.runs.tblog`): the same ``model/*`` and ``time/wall_time_s``
  scalars at step 0.

Training data: every real transition of the file (``lengths`` respected, padding never used). The
trainer's holdout (``model.holdout_ratio``, at most ``model.max_holdout`` transitions, drawn at random)
selects the elites and stops training early. Offline defaults (a fixed data set is seen once, so it
pays to train to convergence; the online loop retrains a little every trial):
``model.max_epochs = 300`` and ``model.patience = 20`` (epochs without a member improving its holdout
error by more than 1 %). ``--epochs N`` (or ``model.max_epochs=N``) overrides the first; ``--epochs``
wins over ``model.max_epochs=``.

``--protocol paper`` trains as the GEM paper did (:mod:`pets.data.protocols`): its config keys, a 100k/10k
train/validation split of the file, and a search over the hidden layers picked on the validation error (an
explicit ``model.hidden_size=`` or ``model.num_layers=`` fixes the architecture instead). The checkpoint's
``offline`` entry records the protocol, the split sizes and every candidate's validation error.

Randomness: ``torch.manual_seed(seed)`` before the ensemble is built (initial weights), and a
generator seeded with ``seed + 1`` on the training device (holdout split, bootstraps, shuffles),
as in the online loop. The same command on the same machine gives the same model.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pets.data.datasets import check_dataset, env_name, load_dataset, transitions
from pets.runs.fileio import locked, new_run_dir_error

#: Offline defaults, applied before the user's overrides (see the module docstring).
OFFLINE_DEFAULTS: dict[str, Any] = {"model.max_epochs": 300, "model.patience": 20}


#: The learning curve of an offline run with ``model.curve_every`` > 0: the holdout error (mean over the members)
#: every ``curve_every`` gradient steps of every searched architecture.
CURVE_FILE = "learning_curve.csv"
CURVE_COLUMNS = ("hidden_size", "num_layers", "step", "holdout_error")


def offline_config(
    env: str,
    head_name: str,
    overrides: Mapping[str, Any] | None = None,
    *,
    preset: str = "research",
    seed: int | None = None,
    device: str | None = None,
    epochs: int | None = None,
    protocol: str = "pets",
):
    """The resolved config of an offline run: config defaults, env defaults, preset, :data:`OFFLINE_DEFAULTS`,
    the protocol's keys, ``overrides``, then the explicit ``seed``/``device``/``epochs`` arguments (later wins).
    ConfigError if bad."""
    from pets.config import ConfigError, make_config
    from pets.data.protocols import get_protocol

    try:
        keys = get_protocol(protocol).config
    except ValueError as err:
        raise ConfigError(str(err)) from None
    merged: dict[str, Any] = {**OFFLINE_DEFAULTS, **keys, **dict(overrides or {})}
    for key, value in (("seed", seed), ("device", device), ("model.max_epochs", epochs)):
        if value is not None:
            merged[key] = value
    return make_config(env, head_name, preset, merged)


def train_offline(
    data: str | Path | Mapping[str, np.ndarray],
    head_name: str,
    out: str | Path,
    overrides: Mapping[str, Any] | None = None,
    *,
    preset: str = "research",
    seed: int | None = None,
    device: str | None = None,
    epochs: int | None = None,
    protocol: str = "pets",
    progress: bool = False,
) -> Path:
    """Train a fresh ensemble with head ``head_name`` on the real transitions of ``data`` under ``protocol``
    (:mod:`pets.data.protocols`) and write run dir ``out``.

    ``data``: a data set file or its arrays (:mod:`pets.data.datasets`). ``out`` must not hold a run yet.
    Returns ``out`` as a Path. ValueError / ConfigError (one-line messages) for bad input.
    """
    import torch

    import envs
    from pets import builder
    from pets.config import ConfigError
    from pets.runs import rundir

    data_label = str(Path(data).resolve()) if isinstance(data, (str, Path)) else None
    arrays = load_dataset(data) if isinstance(data, (str, Path)) else data
    if data_label is None:
        check_dataset(arrays)
    env = envs.get(env_name(arrays)).name
    out = Path(out)
    if (out / rundir.CONFIG_FILE).exists():
        raise ConfigError(f"{out} already holds a run; pick another --out")
    if problem := new_run_dir_error(out):
        raise ConfigError(problem)
    from pets.data.protocols import get_protocol, split_samples

    cfg = offline_config(
        env, head_name, overrides, preset=preset, seed=seed, device=device, epochs=epochs, protocol=protocol
    )
    proto = get_protocol(protocol)
    spec = envs.get(cfg.env)
    obs, act, next_obs = transitions(arrays)
    if obs.shape[-1] != spec.obs_dim or act.shape[-1] != spec.act_dim:
        raise ValueError(
            f"data set has obs_dim {obs.shape[-1]} / act_dim {act.shape[-1]}, but {env} has "
            f"{spec.obs_dim} / {spec.act_dim}"
        )
    fixed = {"model.hidden_size", "model.num_layers"} & set(overrides or {})
    candidates = [] if fixed else list(proto.architectures(cfg.env))
    for hidden, layers in candidates or [(cfg.model.hidden_size, cfg.model.num_layers)]:  # one line, no OOM kill
        sized = cfg.copy()
        sized.model.hidden_size, sized.model.num_layers = hidden, layers
        builder.check_memory(sized, spec, steps=len(obs))
    dev = builder.resolve_device(cfg.device)
    with locked(out):  # one process per run directory (DirectoryInUse for a second one), for the whole training
        if (out / rundir.CONFIG_FILE).exists():  # again: another process may have finished a run there meanwhile
            raise ConfigError(f"{out} already holds a run; pick another --out")
        train_idx, val_idx = split_samples(len(obs), proto)
        if cfg.threads:  # as the online loop: config key threads (0 = torch's default)
            torch.set_num_threads(cfg.threads)

        def tensors(idx: np.ndarray) -> list[torch.Tensor]:
            return [torch.as_tensor(a[idx], dtype=torch.float32, device=dev) for a in (obs, act, next_obs)]

        train_set = tensors(train_idx)
        validation = tensors(val_idx) if len(val_idx) else None
        start, start_cpu = time.perf_counter(), time.process_time()
        architectures = candidates or [(cfg.model.hidden_size, cfg.model.num_layers)]
        result, model, trainer, search = _search(cfg, spec, dev, architectures, train_set, validation, progress)
        wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
        curve = [(e["hidden_size"], e["num_layers"], step, error) for e in search for step, error in e.pop("curve")]

        meta = {
            "data": data_label,
            "episodes": int(len(arrays["lengths"])),
            "transitions": int(obs.shape[0]),
            "data_policy": str(np.asarray(arrays["policy"])[()]) if "policy" in arrays else None,
            "data_seed": int(np.asarray(arrays["seed"])[()]) if "seed" in arrays else None,
            "protocol": proto.name,
            "train_transitions": int(len(train_idx)),
            "validation_transitions": int(len(val_idx)),
            "search": search if candidates else [],
        }
        state, row = _run_state(result, model, trainer, meta, wall, cpu)
        _write_run(out, state, row, cfg, curve)
    return out


def _search(
    cfg: Any,
    spec: Any,
    dev: Any,
    architectures: list[tuple[int, int]],
    train_set: list[Any],
    validation: list[Any] | None,
    progress: bool,
) -> tuple[Any, Any, Any, list[dict[str, Any]]]:
    """Train a model of each ``(hidden_size, num_layers)`` in ``architectures`` (each from the config's seed);
    the best on the validation error (the first where there is none) as ``(result, model, trainer, search)``,
    with ``cfg.model`` set to its architecture."""
    import torch

    from pets import builder
    from pets.models import make_model

    search, best = [], None
    for hidden, layers in architectures:
        cfg.model.hidden_size, cfg.model.num_layers = hidden, layers
        torch.manual_seed(cfg.seed)
        model = make_model(cfg, spec, dev)
        trainer = builder.make_trainer(cfg, model)
        generator = torch.Generator(device=dev).manual_seed(cfg.seed + 1)
        result = trainer.train(*train_set, generator, progress=progress, validation=validation)
        search.append(
            {"hidden_size": hidden, "num_layers": layers, "val_error": result.val_loss, "curve": result.curve}
        )
        if best is None or result.val_loss < best[0].val_loss:  # NaN (no holdout) keeps the first
            best = (result, model, trainer, hidden, layers)
    result, model, trainer, hidden, layers = best
    cfg.model.hidden_size, cfg.model.num_layers = hidden, layers
    return result, model, trainer, search


def _run_state(
    result: Any, model: Any, trainer: Any, meta: dict[str, Any], wall: float, cpu: float
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The checkpoint state of an offline run and its one metrics row (the online columns without a trial)."""
    nan = float("nan")
    row = {
        "trial": nan,
        "env_steps": meta["train_transitions"],
        "episode_reward": nan,
        "episode_length": nan,
        "model_train_loss": result.train_loss,
        "model_val_loss": result.val_loss,
        "model_val_loss_initial": result.initial_val_loss,
        "model_epochs": result.epochs,
        "plan_seconds_per_step": nan,
        "wall_time_s": round(wall, 3),
        "cpu_time_s": round(cpu, 3),
    }
    state = {
        "trials_done": 0,
        "env_steps": 0,
        "wall_time_s": round(wall, 3),
        "cpu_time_s": round(cpu, 3),
        "rows": [row],
        "model": model.state_dict(),
        "trainer": trainer.state_dict(),
        "last_train": result,
        "offline": meta,
    }
    return state, row


def killed_training_files(out: Path) -> list[Path]:
    """The files a training killed (kill -9) while it wrote its run left in ``out``: :func:`_write_run` writes the
    run's files, then config.yaml; where ``out`` has no config.yaml and holds nothing but those files (the lock and
    temporary files aside), they are returned, to be removed before the training runs again; [] otherwise."""
    from pets.runs.fileio import LOCK_FILE, TEMP_SUFFIX
    from pets.runs.rundir import CHECKPOINT_FILE, CONFIG_FILE, METRICS_FILE

    out = Path(out)
    if not out.is_dir() or (out / CONFIG_FILE).exists():
        return []
    skipped = {LOCK_FILE} | {p.name for p in out.glob(f".*{TEMP_SUFFIX}")}
    paths = [p for p in out.iterdir() if p.name not in skipped]
    run_files = (CHECKPOINT_FILE, METRICS_FILE, CURVE_FILE)
    ok = all(p.is_file() and (p.name in run_files or p.name.startswith("events.out.tfevents.")) for p in paths)
    return paths if ok else []


def _write_run(out: Path, state: dict[str, Any], row: dict[str, Any], cfg: Any, curve: list[tuple]) -> None:
    """Write the run's files, config.yaml last (a directory with config.yaml is a complete run); if a write fails
    (a full disk) or Ctrl-C comes, the run's files are removed again and the error propagates (the caller holds the
    lock).
    ``curve``: the ``(hidden_size, num_layers, step, holdout_error)`` rows of :data:`CURVE_FILE`."""
    from pets.runs import rundir
    from pets.runs.fileio import atomic_write_bytes
    from pets.runs.tblog import TRIAL_TAGS, ScalarLog

    try:
        rundir.save_checkpoint(out, state)
        rundir.write_metrics(out, [row])
        if curve:
            lines = [",".join(CURVE_COLUMNS)] + [f"{h},{n},{step},{error!r}" for h, n, step, error in curve]
            atomic_write_bytes(out / CURVE_FILE, ("\n".join(lines) + "\n").encode())
        with ScalarLog(out, cfg.tensorboard, purge_step=0) as log:  # the training result at step 0 (pets.runs.tblog)
            log.scalars(row, 0, {k: v for k, v in TRIAL_TAGS.items() if k.startswith("model_") or k == "wall_time_s"})
        rundir.write_config(out, cfg)
    except BaseException:  # a full disk (OSError) or Ctrl-C: no half-written run is left
        written = [out / rundir.CHECKPOINT_FILE, out / rundir.METRICS_FILE, out / CURVE_FILE]
        for path in [*written, *out.glob("events.out.tfevents.*")]:
            path.unlink(missing_ok=True)
        raise
