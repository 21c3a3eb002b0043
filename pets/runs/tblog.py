"""TensorBoard event files in a run directory, beside metrics.csv (``torch.utils.tensorboard``).

On by default (config key ``tensorboard``); when the ``tensorboard`` package is missing, a run says so in one
line and writes no events (``pip install -e '.[viz]'`` installs it). ``tensorboard --logdir RUN`` shows one
run; ``tensorboard --logdir DIR/runs`` of a ``pets.compare`` output shows each arm's runs side by side.

Tags of an online run (step: ``env_steps``, the reward curve's x): :data:`TRIAL_TAGS`. An offline run
(``pets.train``) writes its training result at step 0 under the same ``model/*`` tags; ``pets.evaluate
--tensorboard`` writes the per-horizon errors as ``eval/METRIC`` with step = the horizon.

Resuming never duplicates a scalar: a resumed run opens its writer with ``purge_step`` = the last
checkpointed ``env_steps`` + 1, which hides whatever an interrupted trial had written after its checkpoint,
and writes only the trials that follow.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: metrics.csv column -> TensorBoard tag (one scalar per trial).
TRIAL_TAGS = {
    "episode_reward": "episode/reward",
    "episode_length": "episode/length",
    "model_train_loss": "model/train_loss",
    "model_val_loss": "model/val_loss",
    "model_val_loss_initial": "model/val_loss_initial",
    "model_epochs": "model/epochs",
    "plan_seconds_per_step": "plan/seconds_per_step",
    "wall_time_s": "time/wall_time_s",
}
MISSING_NOTE = "tensorboard is not installed: no TensorBoard event files (pip install -e '.[viz]' installs it)"


def summary_writer_class() -> Any:
    """``torch.utils.tensorboard.SummaryWriter``, or None when the tensorboard package is missing."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # torch raises ImportError when tensorboard is absent
        return None
    return SummaryWriter


class ScalarLog:
    """The event writer of one run directory; a no-op (after one note on stderr) without tensorboard."""

    def __init__(self, run_dir: str | Path, enabled: bool = True, purge_step: int | None = None) -> None:
        writer_class = summary_writer_class() if enabled else None
        if enabled and writer_class is None:
            print(MISSING_NOTE, file=sys.stderr)
        self.writer = None if writer_class is None else writer_class(str(run_dir), purge_step=purge_step)

    def scalars(self, values: Mapping[str, Any], step: int, tags: Mapping[str, str] | None = None) -> None:
        """Write ``values[key]`` as tag ``tags[key]`` (default: the key itself) at ``step``; NaN/None skipped."""
        if self.writer is None:
            return
        for key, value in values.items():
            if tags is not None and key not in tags:
                continue
            if value is None or not math.isfinite(float(value)):
                continue
            self.writer.add_scalar(tags[key] if tags is not None else key, float(value), int(step))
        self.writer.flush()

    def trial(self, row: Mapping[str, Any]) -> None:
        """One metrics.csv row of an online run, at step ``env_steps``."""
        self.scalars(row, int(row["env_steps"]), TRIAL_TAGS)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def __enter__(self) -> ScalarLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
