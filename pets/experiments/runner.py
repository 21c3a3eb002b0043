"""Running the runs: a :class:`Backend` (a local pool of processes or threads, or Ray), progress and status lines,
and the logged subprocesses of the online runs."""

from __future__ import annotations

import fcntl
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pets.experiments.arguments import PROG, UsageError

#: The repository root: where run_pets.py is and where the runs' subprocesses start.
ROOT = Path(__file__).resolve().parents[2]
#: Jobs: ``(name, fn, args)``; ``fn`` is a module-level function (it may run in another process or on another node).
Jobs = Sequence[tuple[str, Callable[..., Any], tuple]]
#: Results: ``{name: (ok, fn's result or a one-line error message)}``.
Results = dict[str, tuple[bool, Any]]
BACKENDS = ("local", "ray")


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


@contextmanager
def open_backend(backend: Backend, out: Path, needed: bool = True) -> Iterator[Callable[..., Results]]:
    """The backend, ready: a function ``run(jobs, *, processes, progress, desc)`` that runs every job (see
    :func:`run_pool`). Ray (when ``needed``): connected, its resources and the storage under ``out`` checked first
    (UsageError before any work), and disconnected at the end (:mod:`pets.experiments.ray_backend`)."""
    if backend.kind == "ray" and needed:
        from pets.experiments.ray_backend import ray_session

        with ray_session(backend, Path(out)) as run:
            yield run
        return

    def run(jobs: Jobs, *, processes: bool, progress: bool, desc: str) -> Results:
        workers = min(backend.workers, max(len(jobs), 1))
        return run_pool(jobs, workers, processes=processes, progress=progress, desc=desc, threads=backend.threads)

    yield run


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
        """A run started again after its worker or node was lost (always a line)."""
        self.write(f"{name} retried (attempt {attempt}, {where}): its worker or node was lost")

    def close(self) -> Results:
        self.bar.close()
        return self.results


def run_pool(jobs: Jobs, workers: int, *, processes: bool, progress: bool, desc: str, threads: int = 1) -> Results:
    """Run ``fn(*args)`` for every ``(name, fn, args)``; ``{name: (ok, result or error message)}``.

    ``processes``: a spawn ProcessPoolExecutor (workers > 1) or this process (workers = 1); else a thread
    pool (for functions that only wait on subprocesses). A job that raises is reported, the rest go on.
    ``threads``: BLAS/OpenMP threads of every worker process.
    """
    if not jobs:
        return {}
    status = StatusLines(len(jobs), desc, progress)
    record = status.record
    if processes and workers == 1:
        for name, fn, args in jobs:
            try:
                record(name, True, fn(*args))
            except Exception as err:  # one failed run must not stop the others
                record(name, False, one_line(err))
    else:
        if processes:
            import multiprocessing

            pool: Any = ProcessPoolExecutor(
                max_workers=workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_worker_init,
                initargs=(threads,),
            )
        else:
            pool = ThreadPoolExecutor(max_workers=workers)
        with pool:
            futures: dict[Future, str] = {pool.submit(fn, *args): name for name, fn, args in jobs}
            for fut in as_completed(futures):
                err = fut.exception()
                record(futures[fut], err is None, fut.result() if err is None else one_line(err))
    return status.close()


def thread_env(threads: int) -> dict[str, str]:
    """Environment variables that give BLAS/OpenMP ``threads`` threads."""
    return {name: str(threads) for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}


def _worker_init(threads: int) -> None:
    """``threads`` CPU threads per worker (set before it imports torch; the jobs also set torch's thread count)."""
    os.environ.update(thread_env(threads))


def _die_with_parent() -> None:  # pragma: no cover - runs in the forked child
    """Linux: the child gets SIGKILL when the process that started it dies (a killed Ray worker leaves no orphan
    run holding the run directory's lock)."""
    import ctypes
    import signal

    ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def run_logged(command: Sequence[str], log: Path, threads: int = 1) -> int:
    """Run ``command`` with ``threads`` CPU threads, appending its output to ``log``; raise if it fails."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        where = f"{socket.gethostname()} pid {os.getpid()}"
        f.write(f"\n[{time.strftime('%Y-%m-%d %H:%M:%S')}] ({where}) {' '.join(command)}\n")
        f.flush()
        proc = subprocess.run(
            command,
            stdout=f,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
            env={**os.environ, **thread_env(threads)},
            preexec_fn=_die_with_parent if sys.platform == "linux" else None,
        )
    if proc.returncode != 0:
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        raise RuntimeError(f"exit {proc.returncode}; log {log}; last line: {lines[-1] if lines else ''}")
    return proc.returncode


def wait_until_unlocked(run_dir: Path, timeout: float = 60.0) -> None:
    """Wait (up to ``timeout`` s) until no process holds ``run_dir``'s lock: a run killed with its worker releases it
    when the kernel has reaped it, which may be just after the retry starts."""
    from pets.fileio import LOCK_FILE

    path = Path(run_dir) / LOCK_FILE
    if not path.exists():
        return
    deadline = time.monotonic() + timeout
    fd = os.open(path, os.O_RDONLY)
    try:
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                fcntl.flock(fd, fcntl.LOCK_UN)
                return
            except BlockingIOError:
                if time.monotonic() > deadline:
                    return  # the run itself then says who holds it
                time.sleep(0.2)
    finally:
        os.close(fd)


def online_job(run_dir: str, start_args: Sequence[str], trials: int, log: str, threads: int = 1) -> str:
    """Start or resume one online run, decided when the job runs (a retried job resumes what its first attempt
    began); ``"start"`` or ``"resume"``. ``start_args``: run_pets.py's arguments for a new run."""
    run_path = Path(run_dir)
    script = [sys.executable, str(ROOT / "run_pets.py")]
    if (run_path / "config.yaml").is_file():
        wait_until_unlocked(run_path)
        run_logged([*script, "--resume", run_dir, "--trials", str(trials), "--quiet"], Path(log), threads)
        return "resume"
    run_logged([*script, *start_args], Path(log), threads)
    return "start"
