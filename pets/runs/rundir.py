"""The run directory: resolved config, per-trial metrics, atomic checkpoints and the reward plot.

Every file is written to a temporary name and moved into place with ``os.replace``, so a run
killed at any moment (even ``kill -9``) leaves either the old or the new version, never half a file.
"""

from __future__ import annotations

import csv
import io
import os
import pickle
import re
import socket
import time
import types
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from pets.errors import ConfigError
from pets.runs.fileio import CONFIG_FILE, atomic_write_bytes

METRICS_FILE = "metrics.csv"
CHECKPOINT_FILE = "checkpoint.pt"
PLOT_FILE = "rewards.png"
#: One row per session of a run (start or resume): when, where, and how many trials were done when it began.
HISTORY_FILE = "history.csv"
#: Written when a run stops because its model training diverged or no plan had a finite return (its last line: why);
#: removed when the run is resumed. A comparison counts such a run as diverged: the worst outcome, never dropped.
DIVERGED_FILE = "diverged.txt"
HISTORY_COLUMNS = ["time", "action", "trials_done", "host", "pid", "cpu"]

#: model_val_loss: the trainer's holdout error of the selected model after the trial's training;
#: model_val_loss_initial: the same for the weights that training started from (a trained model has less).
METRIC_COLUMNS = [
    "trial",
    "env_steps",
    "episode_reward",
    "episode_length",
    "terminated",
    "model_train_loss",
    "model_val_loss",
    "model_val_loss_initial",
    "model_epochs",
    "plan_seconds_per_step",
    "plan_cpu_s",
    "train_cpu_s",
    "value_cpu_s",
    "wall_time_s",
    "cpu_time_s",
]
#: The columns of metrics.csv that measure time, not what the run did: a resumed or repeated run with the same seed
#: repeats every other column. ``cpu_time_s``: the run's process CPU seconds (all its threads; not the compile
#: workers inductor starts as other processes), cumulative like ``wall_time_s``; NaN for a run resumed from a
#: checkpoint written before the column existed. ``plan_cpu_s``, ``train_cpu_s``, ``value_cpu_s``: the trial's
#: planning, model training and terminal-value fit in process CPU seconds (the rest of the trial's share of
#: ``cpu_time_s`` is the simulator and the run's own bookkeeping; nan in rows written before the columns existed).
TIMING_COLUMNS = ("plan_seconds_per_step", "plan_cpu_s", "train_cpu_s", "value_cpu_s", "wall_time_s", "cpu_time_s")


def write_config(run_dir: Path, cfg: DictConfig) -> None:
    atomic_write_bytes(run_dir / CONFIG_FILE, OmegaConf.to_yaml(cfg, resolve=True).encode())


def write_metrics(run_dir: Path, rows: list[dict[str, Any]]) -> None:
    """Rewrite metrics.csv from the full list of rows (one per completed trial; never duplicates)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=METRIC_COLUMNS, extrasaction="ignore", restval="nan")  # a later column
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(run_dir / METRICS_FILE, buf.getvalue().encode())


def append_history(run_dir: Path, action: str, trials_done: int) -> None:
    """Add this session (``start`` or ``resume`` at ``trials_done`` trials) to history.csv: a resumed run shows
    that it went on from its checkpoint, not from trial 0, and the CPU of every session names the machine behind
    its CPU-hours (a history written before the ``cpu`` column gets it, empty in its old rows). A damaged history
    (bytes that are not text) keeps its rows as they read, never stopping the run: it only records the sessions."""
    from pets.runs.hardware import cpu_name

    path = run_dir / HISTORY_FILE
    _, _, rows = (path.read_text(errors="replace") if path.is_file() else "").partition("\n")  # header anew
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(HISTORY_COLUMNS)
    now = time.strftime("%Y-%m-%dT%H:%M:%S")
    writer.writerow([now, action, trials_done, socket.gethostname(), os.getpid(), cpu_name()])
    head, _, new = buf.getvalue().partition("\n")
    atomic_write_bytes(path, f"{head}\n{rows}{new}".encode())


def written_config(run_dir: Path) -> dict[str, Any]:
    """A run's config.yaml as written (nested dicts; a key added to the schema after the run is absent, not filled
    with its default)."""
    import yaml

    return yaml.safe_load((run_dir / CONFIG_FILE).read_text()) or {}


def record_divergence(run_dir: Path, why: str | None) -> None:
    """Record why the run in ``run_dir`` stopped diverged (:data:`DIVERGED_FILE`), or with None clear the record."""
    if why is None:
        (run_dir / DIVERGED_FILE).unlink(missing_ok=True)
    else:
        atomic_write_bytes(run_dir / DIVERGED_FILE, f"{why}\n".encode())


def read_divergence(run_dir: Path) -> str | None:
    """Why the run in ``run_dir`` stopped diverged (:func:`record_divergence`), or None if it did not. The file's
    presence is the record: damaged bytes in it (not text) read as they can, never an error."""
    path = run_dir / DIVERGED_FILE
    return (path.read_text(errors="replace").strip() or "diverged") if path.is_file() else None


def read_history(run_dir: Path) -> list[dict[str, str]]:
    """The rows of a run's history.csv (empty if it has none)."""
    path = run_dir / HISTORY_FILE
    if not path.is_file():
        return []
    with open(path, newline="", errors="replace") as f:  # damaged bytes: the rows as they read
        return list(csv.DictReader(f))


def read_metrics(path: Path) -> list[dict[str, float]]:
    """Read a metrics.csv into rows of floats."""
    with open(path, newline="") as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


#: Modules that moved after checkpoints were written, old path -> new: a checkpoint pickles its ``last_train``
#: (a ``TrainResult``) by its module path, ``pets.trainer`` before the library moved into subpackages (issue 33).
MOVED_MODULES = {"pets.trainer": "pets.learning.trainer"}


class _Unpickler(pickle.Unpickler):
    """pickle's Unpickler that finds the classes of :data:`MOVED_MODULES` at their new paths."""

    def find_class(self, module: str, name: str) -> Any:
        return super().find_class(MOVED_MODULES.get(module, module), name)


#: ``pickle`` with :class:`_Unpickler`, for ``torch.load(pickle_module=...)``.
_CHECKPOINT_PICKLE = types.ModuleType("checkpoint_pickle")
vars(_CHECKPOINT_PICKLE).update({k: v for k, v in vars(pickle).items() if not k.startswith("__")})
_CHECKPOINT_PICKLE.Unpickler = _Unpickler


def save_checkpoint(run_dir: Path, state: dict[str, Any]) -> None:
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(run_dir / CHECKPOINT_FILE, buf.getvalue())


def load_checkpoint(run_dir: Path) -> dict[str, Any] | None:
    """The checkpoint's state (None when there is none yet); ConfigError for a file torch cannot read."""
    path = run_dir / CHECKPOINT_FILE
    if not path.exists():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=False, pickle_module=_CHECKPOINT_PICKLE)
    except Exception as err:  # truncated (full disk), empty or foreign file: pickle, zip and torch errors alike
        reason = _first_sentence(str(err))
        raise ConfigError(
            f"{path} is not a readable checkpoint ({type(err).__name__}: {reason}); "
            "restore it from a copy, or delete it to start the run over"
        ) from None
    if not isinstance(state, dict):
        raise ConfigError(f"{path} is not a checkpoint of this program (it holds a {type(state).__name__})")
    return state


def load_model_state(model: torch.nn.Module, state: dict[str, Any]) -> None:
    """Load a checkpoint's model weights into ``model``; ConfigError for an older format or a model that does not
    match (a config.yaml edited after the run started)."""
    if "model" not in state:
        raise ConfigError(
            "this checkpoint was written by an older gem-pets (< 0.2, before models standardised their targets): "
            "train the model again"
        )
    try:
        model.load_state_dict(state["model"])
    except (RuntimeError, ValueError) as err:
        mismatches = re.findall(
            r"size mismatch for ([\w.]+): copying a param with shape torch.Size\((\[[^]]*\])\) "
            r"from checkpoint, the shape in current model is torch.Size\((\[[^]]*\])\)",
            str(err),
        )
        if mismatches:
            name, saved, now = mismatches[0]
            more = f" (and {len(mismatches) - 1} more)" if len(mismatches) > 1 else ""
            detail = f"{name} is {saved} in the checkpoint but {now} under config.yaml{more}"
        else:
            detail = _first_sentence(re.sub(r"^Error\(s\) in loading state_dict for \w+:", "", str(err)))
        raise ConfigError(
            f"the checkpoint's model does not match config.yaml (was config.yaml edited?): {detail}; put back the "
            "config.yaml the run was started with, or start a new run"
        ) from None


#: Keys a resume may change: how many trials the run goes to (``--resume DIR --trials N``) and the CPU threads
#: (``threads=1`` on a shared machine), which change no result.
RESUMABLE_KEYS = ("trials", "threads")


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix[:-1]: d}
    return {k: v for key, value in d.items() for k, v in _flat(value, f"{prefix}{key}.").items()}


def check_resumed_config(run_dir: Path, state: dict[str, Any], cfg: Any) -> None:
    """ConfigError when config.yaml no longer says what the checkpoint was written with (an edit after the run
    started: the run would go on with the checkpoint's optimiser state and claim the edited values). Checkpoints
    from before the config was saved in them are not checked; nor is a key in neither the checkpoint nor the file
    (added to the code after the run started: it takes its default, which keeps what the code did before it), nor
    ``imports`` that keeps every module the checkpoint records and adds others (a run from before the key, or one
    whose model or planner was registered by a module the process imported itself: its config.yaml may be given the
    modules that register them, which change no result)."""
    from omegaconf import OmegaConf

    if not isinstance(state.get("config"), dict):
        return
    saved, now = _flat(state["config"]), _flat(OmegaConf.to_container(cfg))
    written = _flat(written_config(run_dir))
    keys = saved.keys() | written.keys()
    added = set(saved.get("imports") or []) <= set(now.get("imports") or [])
    same = (*RESUMABLE_KEYS, *(("imports",) if added else ()))
    changed = sorted(k for k in keys if k not in same and saved.get(k) != now.get(k))
    if changed:
        first = changed[0]
        raise ConfigError(
            f"{run_dir / CONFIG_FILE} was edited after the run started ({first}: {saved.get(first)!r} in the "
            f"checkpoint, {now.get(first)!r} in config.yaml; keys edited: {', '.join(changed)}); put back the config "
            "the run was started with (a resume may change only trials and threads, and add modules to imports), "
            "or start a new run"
        )


def check_finite_buffer(run_dir: Path, buffer: dict[str, Any]) -> None:
    """ConfigError when the checkpoint's replay buffer holds NaN or inf (a damaged file: training on it would fail
    with a traceback, or silently learn from it)."""
    import numpy as np

    bad = [name for name, values in buffer.items() if not np.isfinite(np.asarray(values)).all()]
    if bad:
        raise ConfigError(
            f"{run_dir / CHECKPOINT_FILE} holds non-finite values (NaN or inf) in its replay buffer "
            f"({', '.join(bad)}): the file is damaged; restore it from a copy, or delete it to start the run over"
        )


def recorded_trials(run_dir: Path) -> int:
    """How many completed trials the run directory's metrics.csv and history.csv record (0 when they record none,
    are missing or unreadable): a run that has them has had a checkpoint."""
    count = 0
    try:
        with open(run_dir / METRICS_FILE, newline="", errors="replace") as f:
            count = sum(1 for _ in csv.DictReader(f))
    except (OSError, csv.Error):
        pass
    try:
        done = [int(row.get("trials_done") or 0) for row in read_history(run_dir)]
    except (OSError, csv.Error, ValueError):
        done = []
    return max([count, *done])


def missing_checkpoint_message(run_dir: Path) -> str:
    """The one line that refuses to resume a run whose checkpoint.pt is gone although it completed trials (it would
    start over from trial 0 and rewrite metrics.csv)."""
    return (
        f"{run_dir / CHECKPOINT_FILE} is missing although the run records {recorded_trials(run_dir)} completed "
        f"trial(s) (metrics.csv, history.csv): resuming would start over from trial 0 and rewrite them; restore "
        "checkpoint.pt from a copy, or start a new run in another directory"
    )


def _first_sentence(text: str, limit: int = 160) -> str:
    """The first sentence of an error message, on one line and at most ``limit`` characters."""
    line = " ".join(text.split())
    first = re.split(r"(?<=\.) ", line, maxsplit=1)[0].rstrip(".")
    return first if len(first) <= limit else first[: limit - 3] + "..."


def plot_rewards(run_dir: Path, rows: list[dict[str, Any]], title: str) -> None:
    """Episode reward against environment steps, written atomically to rewards.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([r["env_steps"] for r in rows], [r["episode_reward"] for r in rows], marker="o", ms=3)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode reward")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(run_dir / PLOT_FILE, buf.getvalue())


def stopped(rows: list[dict[str, Any]], stop_reward: float | None, max_env_steps: int | None = None) -> bool:
    """Whether a run is done before its ``trials``: some trial's episode reward reached ``stop_reward``, or the env
    steps reached the budget ``max_env_steps`` (either None: never)."""
    if stop_reward is not None and any(float(r["episode_reward"]) >= stop_reward for r in rows):
        return True
    return max_env_steps is not None and bool(rows) and int(rows[-1]["env_steps"]) >= max_env_steps
