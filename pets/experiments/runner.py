"""Running the runs: a pool of jobs (processes, threads or this process) and logged one-thread subprocesses."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from pets.experiments.arguments import PROG

#: The repository root: where run_pets.py is and where the runs' subprocesses start.
ROOT = Path(__file__).resolve().parents[2]
#: Environment of every run: one BLAS/OpenMP thread.
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def run_pool(
    jobs: Sequence[tuple[str, Callable[..., Any], tuple]], workers: int, *, processes: bool, progress: bool, desc: str
) -> dict[str, tuple[bool, Any]]:
    """Run ``fn(*args)`` for every ``(name, fn, args)``; ``{name: (ok, result or error message)}``.

    ``processes``: a spawn ProcessPoolExecutor (workers > 1) or this process (workers = 1); else a thread
    pool (for functions that only wait on subprocesses). A job that raises is reported, the rest go on.
    """
    from tqdm.auto import tqdm

    results: dict[str, tuple[bool, Any]] = {}
    if not jobs:
        return results
    bar = tqdm(total=len(jobs), desc=desc, unit="run", disable=not progress, file=sys.stderr)

    def record(name: str, ok: bool, value: Any) -> None:
        results[name] = (ok, value)
        if not ok:
            tqdm.write(f"{PROG}: {name} failed: {value}", file=sys.stderr)
        bar.update(1)

    if processes and workers == 1:
        for name, fn, args in jobs:
            try:
                record(name, True, fn(*args))
            except Exception as err:  # one failed run must not stop the others
                record(name, False, f"{type(err).__name__}: {' '.join(str(err).split())}")
    else:
        if processes:
            import multiprocessing

            pool: Any = ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init
            )
        else:
            pool = ThreadPoolExecutor(max_workers=workers)
        with pool:
            futures: dict[Future, str] = {pool.submit(fn, *args): name for name, fn, args in jobs}
            for fut in as_completed(futures):
                err = fut.exception()
                if err is None:
                    record(futures[fut], True, fut.result())
                else:
                    record(futures[fut], False, f"{type(err).__name__}: {' '.join(str(err).split())}")
    bar.close()
    return results


def _worker_init() -> None:
    """One CPU thread per worker (set before the worker imports torch; the jobs also call set_num_threads(1))."""
    os.environ.update(ONE_THREAD_ENV)


def run_logged(command: Sequence[str], log: Path) -> int:
    """Run ``command`` with one CPU thread, appending its output to ``log``; raise if it fails."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        f.write(f"\n[{time.strftime('%Y-%m-%d %H:%M:%S')}] {' '.join(command)}\n")
        f.flush()
        proc = subprocess.run(
            command, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, env={**os.environ, **ONE_THREAD_ENV}
        )
    if proc.returncode != 0:
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        raise RuntimeError(f"exit {proc.returncode}; log {log}; last line: {lines[-1] if lines else ''}")
    return proc.returncode
