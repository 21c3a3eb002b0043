"""What the backends share: the :class:`Backend` settings, jobs and results, and the driver's status lines."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from pets.experiments.arguments import PROG, UsageError

#: Jobs: ``(name, fn, args)``; ``fn`` is a module-level function (it may run in another process or on another node).
Jobs = Sequence[tuple[str, Callable[..., Any], tuple]]
#: Results: ``{name: (ok, fn's result or a one-line error message)}``.
Results = dict[str, tuple[bool, Any]]
BACKENDS = ("local", "ray")


class RunKilled(RuntimeError):
    """A run's process was killed by a signal from outside the sweep (the kernel's out-of-memory killer, a
    scheduler): on Ray its task is retried and the run resumes, as when its worker dies (docs/cluster.md)."""


@dataclass(frozen=True)
class Backend:
    """Where the runs of a comparison run, and with how many CPU threads each.

    ``local``: a pool of ``workers`` processes (or threads waiting on subprocesses) on this machine. ``ray``: one Ray
    task per run asking for ``threads`` CPUs (and ``gpus`` GPUs), on a new local Ray instance (``address`` None) or
    an existing cluster (``"auto"``, ``"ray://HOST:10001"``); a task whose worker or node dies is retried up to
    ``max_retries`` times (an online run resumes from its last checkpoint).
    """

    kind: str = "local"
    workers: int = 1
    threads: int = 1
    address: str | None = None
    gpus: float = 0.0
    max_retries: int = 3

    def __post_init__(self) -> None:
        if self.kind not in BACKENDS:
            raise UsageError(f"unknown backend {self.kind!r}; accepted: {', '.join(BACKENDS)}")
        if self.workers < 1 or self.threads < 1 or self.max_retries < 0:
            raise UsageError(
                f"--workers and --threads must be >= 1 and --max-retries >= 0, "
                f"got {self.workers}, {self.threads}, {self.max_retries}"
            )
        if self.kind == "local" and self.address is not None:
            raise UsageError("--address is for --backend ray (the local backend runs on this machine)")

    def describe(self) -> str:
        """``2 local workers x 1 thread`` or ``Ray (local instance), 1 CPU per run``."""
        if self.kind == "local":
            return f"{self.workers} local worker{'s' if self.workers > 1 else ''} x {self.threads} thread(s)"
        where = "new local instance" if self.address is None else self.address
        return f"Ray ({where}), {self.threads} CPU{'s' if self.threads > 1 else ''} per run"


def one_line(err: BaseException) -> str:
    """``Type: message`` of an exception, on one line."""
    return f"{type(err).__name__}: {' '.join(str(err).split())}"


class StatusLines:
    """The driver's view of the runs: one bar over runs and a line per finished, failed or retried run."""

    def __init__(self, total: int, desc: str, progress: bool) -> None:
        from tqdm.auto import tqdm

        self._tqdm = tqdm
        self.progress = progress
        self.bar = tqdm(total=total, desc=desc, unit="run", disable=not progress, file=sys.stderr)
        self.results: Results = {}
        self.started = time.perf_counter()

    def write(self, line: str) -> None:
        self._tqdm.write(f"{PROG}: {line}", file=sys.stderr)

    def record(self, name: str, ok: bool, value: Any) -> None:
        """A run ended: finished (a line unless quiet) or failed (always a line, with the reason)."""
        self.results[name] = (ok, value)
        if not ok:
            self.write(f"{name} failed: {value}")
        elif self.progress:
            self.write(f"{name} finished ({time.perf_counter() - self.started:.0f} s into the sweep)")
        self.bar.update(1)

    def retried(self, name: str, attempt: int, where: str) -> None:
        """A run started again after its worker or node was lost, or its process was killed (always a line)."""
        self.write(f"{name} retried (attempt {attempt}, {where}): its worker or node was lost, or its process killed")

    def close(self) -> Results:
        self.bar.close()
        return self.results
