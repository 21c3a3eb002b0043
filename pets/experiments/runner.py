"""Running the runs: the backend opened (:func:`open_backend`: a local pool of processes or threads, or Ray) and the
logged subprocesses of the online runs (:func:`online_job`)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

from pets.experiments.arguments import UsageError
from pets.experiments.backend import Backend, Jobs, Results, RunKilled, StatusLines, one_line
from pets.runs.fileio import DirectoryInUse, locked

#: The repository root: where run_pets.py is and where the runs' subprocesses start.
ROOT = Path(__file__).resolve().parents[2]
#: Seconds an interrupted sweep's subprocesses get to exit after SIGINT before SIGKILL.
STOP_GRACE_SECONDS = 10.0

# The live subprocesses of :func:`run_logged` in this process, and whether a sweep was interrupted (then no more
# start): :func:`_stop_sweep` stops them.
_children: set[subprocess.Popen] = set()
_children_lock = threading.Lock()
_interrupted = threading.Event()


@contextmanager
def sweep_lock(out: Path) -> Iterator[None]:
    """Hold ``out``'s lock (:func:`pets.runs.fileio.locked`) while a sweep runs and writes its summaries; UsageError
    (one line) while another command holds it: two sweeps in one directory would fail each other's runs (every run
    directory is locked) and overwrite each other's summaries."""
    with ExitStack() as stack:
        try:
            stack.enter_context(locked(out))
        except DirectoryInUse as err:
            raise UsageError(
                f"{out} is in use by another command (process {err.holder}); one sweep at a time in a directory: "
                "wait for it, or pick another --out"
            ) from None
        yield


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


def run_pool(jobs: Jobs, workers: int, *, processes: bool, progress: bool, desc: str, threads: int = 1) -> Results:
    """Run ``fn(*args)`` for every ``(name, fn, args)``; ``{name: (ok, result or error message)}``.

    ``processes``: a spawn ProcessPoolExecutor (workers > 1) or this process (workers = 1); else a thread
    pool (for functions that only wait on subprocesses). A job that raises is reported, the rest go on.
    ``threads``: BLAS/OpenMP threads of every worker process. An interrupt (KeyboardInterrupt) cancels the jobs not
    started and stops the running ones (:func:`_stop_sweep`) before it propagates.
    """
    if not jobs:
        return {}
    _interrupted.clear()
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
            try:
                for fut in as_completed(futures):
                    err = fut.exception()
                    record(futures[fut], err is None, fut.result() if err is None else one_line(err))
            except BaseException:  # Ctrl-C or SIGINT: the sweep stops, not only the runs that were running
                _stop_sweep(pool, processes)
                raise
    return status.close()


def _stop_sweep(pool: Any, processes: bool) -> None:
    """An interrupted sweep: no job starts any more, and the running ones stop (an online run resumes from its last
    completed trial, an offline job is redone whole): the worker processes get SIGTERM; the online runs'
    subprocesses SIGINT (run_pets.py exits as on Ctrl-C), SIGKILL after :data:`STOP_GRACE_SECONDS`."""
    workers = list((getattr(pool, "_processes", None) or {}).values())  # shutdown() forgets them
    pool.shutdown(wait=False, cancel_futures=True)
    if processes:  # jobs already handed to a worker are not cancelled: stop the workers themselves
        for worker in workers:
            worker.terminate()
        return
    with _children_lock:
        _interrupted.set()
        children = list(_children)
    for child in children:
        child.send_signal(signal.SIGINT)
    deadline = time.monotonic() + STOP_GRACE_SECONDS
    for child in children:
        try:
            child.wait(max(deadline - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            child.kill()


def thread_env(threads: int) -> dict[str, str]:
    """Environment variables that give BLAS/OpenMP ``threads`` threads."""
    return {name: str(threads) for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}


def _worker_init(threads: int) -> None:
    """``threads`` CPU threads per worker (set before it imports torch; the jobs also set torch's thread count);
    the worker dies with the sweep's process (a killed driver leaves no orphan computing a job)."""
    os.environ.update(thread_env(threads))
    if sys.platform == "linux":
        _die_with_parent()


def _die_with_parent() -> None:  # pragma: no cover - runs in the child or pool worker
    """Linux: the child gets SIGKILL when the process that started it dies (a killed Ray worker leaves no orphan
    run holding the run directory's lock)."""
    import ctypes
    import signal

    ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def _sigint_default() -> None:  # pragma: no cover - runs in the child
    """SIGINT back to its default in a run's process, which a sweep started in the background (``&``, nohup: SIGINT
    ignored, inherited through exec) would pass on: :func:`_stop_sweep` stops the runs with SIGINT."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _run_child() -> None:  # pragma: no cover - runs in the child
    """``preexec_fn`` of a run's process on Linux: :func:`_sigint_default` and :func:`_die_with_parent`."""
    _sigint_default()
    _die_with_parent()


def run_logged(command: Sequence[str], log: Path, threads: int = 1) -> int:
    """Run ``command`` with ``threads`` CPU threads, appending its output to ``log``; raise if it fails. It starts in
    the repository with the current folder on PYTHONPATH (a user's env ``--envs mymodule:SPEC`` imports there)."""
    from envs.custom import child_environment

    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        with _children_lock:  # registered before an interrupt can miss it; none starts (nor is logged) after one
            if _interrupted.is_set():
                raise RuntimeError("not started: the sweep was interrupted")
            where = f"{socket.gethostname()} pid {os.getpid()}"
            f.write(f"\n[{time.strftime('%Y-%m-%d %H:%M:%S')}] ({where}) {' '.join(command)}\n")
            f.flush()
            proc = subprocess.Popen(
                command,
                stdout=f,
                stderr=subprocess.STDOUT,
                cwd=ROOT,
                env=child_environment({**os.environ, **thread_env(threads)}),  # your env imports from your folder
                preexec_fn=_run_child if sys.platform == "linux" else _sigint_default,
            )
            _children.add(proc)
        try:
            proc.wait()
        finally:
            with _children_lock:
                _children.discard(proc)
    if proc.returncode != 0:
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        # SIGKILL or SIGTERM from outside the sweep (the OOM killer, a scheduler); a crash (SIGSEGV) is the run's own
        killed = -proc.returncode in (signal.SIGKILL, signal.SIGTERM) and not _interrupted.is_set()
        raise (RunKilled if killed else RuntimeError)(
            f"exit {proc.returncode}; log {log}; last line: {lines[-1] if lines else ''}"
        )
    return proc.returncode


def wait_until_unlocked(run_dir: Path, timeout: float = 60.0) -> None:
    """Wait (up to ``timeout`` s) until no process holds ``run_dir``'s lock (:func:`pets.runs.fileio.locked`): a run
    killed with its worker releases it when the kernel has reaped it, which may be just after the retry starts."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            with locked(run_dir):
                return
        except DirectoryInUse:
            if time.monotonic() > deadline:
                return  # the run itself then says who holds it
            time.sleep(0.2)


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
