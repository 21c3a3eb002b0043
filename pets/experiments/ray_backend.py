"""The Ray backend: one Ray task per run, retried when its worker or node is lost, run directories on shared storage.

The driver (this process) connects to Ray, checks that every node can write ``--out`` and that the driver sees
what they write, submits one task per job, and follows them: a bar over runs and a status line per finished,
failed or retried run. A task records each attempt with a small status actor, so a retry is reported as it starts.
Ray retries only system failures (worker or node died), never a run that failed by itself. docs/cluster.md.
"""

from __future__ import annotations

import logging
import os
import socket
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pets.experiments.arguments import UsageError
from pets.experiments.backend import Backend, Jobs, Results, RunKilled, StatusLines, one_line

#: Seconds between two looks at the tasks (status lines of retries appear within this).
POLL_S = 1.0
#: Seconds a storage probe may take on a node before the check fails.
PROBE_TIMEOUT_S = 120.0


def require_ray() -> Any:
    """The ``ray`` module; UsageError with the install command if it is missing."""
    try:
        import ray
    except ImportError:
        raise UsageError("--backend ray needs Ray: pip install 'gem-pets[ray]' (or pip install 'ray>=2.40')") from None
    return ray


def connect(backend: Backend) -> Any:
    """Connect to the backend's cluster (``address`` None: start a local instance) unless this process already is;
    the ``ray`` module."""
    ray = require_ray()
    if ray.is_initialized():
        return ray
    if backend.address is None:  # a private instance for one sweep; a cluster's own auth mode and token are kept
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")
        # Ray starts its workers at niceness 15; the runs are this instance's whole work, so they run at the
        # driver's priority, as the local backend's do (at 15, beside any other busy process, they got a sliver of
        # a core: a small sweep took 13x the local backend's time). A cluster keeps its own setting (docs/cluster.md).
        os.environ.setdefault("RAY_worker_niceness", "0")
    from envs.custom import child_environment

    # Every worker imports from the folder the command runs in, as a local run does (--envs mymodule:SPEC): the
    # driver's PYTHONPATH and its current folder (on a cluster, a folder on the shared storage: docs/cluster.md)
    runtime_env = {"env_vars": {"PYTHONPATH": child_environment()["PYTHONPATH"]}}
    try:
        ray.init(
            address="local" if backend.address is None else backend.address,
            runtime_env=runtime_env,
            include_dashboard=False,
            log_to_driver=False,
            logging_level=logging.ERROR,
        )
    except (ConnectionError, RuntimeError, ValueError) as err:
        reason = " ".join(str(err).split())[:200]
        raise UsageError(
            f"cannot connect to Ray at {backend.address or 'a new local instance'} ({reason}); "
            "start the cluster with `ray start --head` (docs/cluster.md) or check --address; a cluster with token "
            "authentication (the default of `ray start` since Ray 2.59) needs RAY_AUTH_MODE=token and its token "
            "(RAY_AUTH_TOKEN or ~/.ray/auth_token) in this shell, or --address auto on its head node"
        ) from None
    return ray


def _probe(out: str, token: str) -> tuple[str, str | None]:
    """On one node: write ``out/.ray-probe-TOKEN-HOST``; (host, why it failed or None)."""
    host = socket.gethostname()
    path = Path(out) / f".ray-probe-{token}-{host}-{os.getpid()}"
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
        path.write_text(token)
    except OSError as err:
        return host, f"{err.strerror or err} ({path.parent})"
    return host, str(path)


def check_shared_storage(ray: Any, out: Path) -> None:
    """UsageError unless a task on every alive node can write into ``out`` and this process reads what it wrote."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    token = uuid.uuid4().hex[:12]
    probe = ray.remote(num_cpus=0, max_retries=0)(_probe)
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    refs = [
        probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote(
            str(out), token
        )
        for n in nodes
    ]
    try:
        answers = ray.get(refs, timeout=PROBE_TIMEOUT_S)
    except ray.exceptions.GetTimeoutError:
        raise UsageError(f"the storage check of --out {out} took over {PROBE_TIMEOUT_S:.0f} s on some node") from None
    try:
        for node, (host, result) in zip(nodes, answers):
            where = f"node {host} ({node.get('NodeManagerAddress')})"
            if not result.startswith(str(out)):
                raise UsageError(
                    f"--out {out} is not writable from {where}: {result}; on a cluster --out must be a shared "
                    "file system path every node can write (docs/cluster.md)"
                )
            if not Path(result).is_file() or Path(result).read_text() != token:
                raise UsageError(
                    f"a file written into --out {out} by {where} is not visible here: --out must be on a file "
                    "system shared by every node and this machine (NFS, Lustre, ...; docs/cluster.md)"
                )
    finally:
        for path in out.glob(f".ray-probe-{token}-*"):
            path.unlink(missing_ok=True)


def check_resources(ray: Any, backend: Backend) -> None:
    """UsageError if no node has the CPUs (and GPUs) one run asks for: such a task would wait forever."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    if not any(r.get("CPU", 0) >= backend.threads and r.get("GPU", 0) >= backend.gpus for r in nodes):
        most = max((r.get("CPU", 0) for r in nodes), default=0)
        gpus = max((r.get("GPU", 0) for r in nodes), default=0)
        raise UsageError(
            f"every run asks for {backend.threads} CPU(s) and {backend.gpus:g} GPU(s), but the largest Ray node has "
            f"{most:g} CPU(s) and {gpus:g} GPU(s); lower --threads or add nodes"
        )


class _Attempts:
    """A Ray actor that counts each run's attempts and queues them for the driver."""

    def __init__(self) -> None:
        self.count: dict[str, int] = {}
        self.new: list[tuple[str, int, str]] = []

    def started(self, name: str, where: str) -> int:
        self.count[name] = self.count.get(name, 0) + 1
        self.new.append((name, self.count[name], where))
        return self.count[name]

    def drain(self) -> list[tuple[str, int, str]]:
        new, self.new = self.new, []
        return new


def _attempt(board: Any, name: str, fn: Callable[..., Any], args: tuple) -> Any:
    """One attempt of one job, in a Ray worker: report it, then run ``fn(*args)``."""
    import ray

    ray.get(board.started.remote(name, f"{socket.gethostname()} pid {os.getpid()}"))
    return fn(*args)


@contextmanager
def ray_session(backend: Backend, out: Path) -> Iterator[Callable[..., Results]]:
    """Connected and checked (resources, shared storage): yields ``run(jobs, *, processes, progress, desc)``;
    disconnects at the end (a Ray session the caller opened stays open)."""
    owned = not require_ray().is_initialized()
    ray = connect(backend)
    try:
        check_resources(ray, backend)
        check_shared_storage(ray, out)

        def run(jobs: Jobs, *, processes: bool, progress: bool, desc: str) -> Results:
            return run_tasks(ray, jobs, backend, progress=progress, desc=desc)

        yield run
    finally:
        if owned:
            ray.shutdown()


def run_tasks(ray: Any, jobs: Jobs, backend: Backend, *, progress: bool, desc: str) -> Results:
    """Run every ``(name, fn, args)`` as a Ray task; ``{name: (ok, result or error message)}`` like the local pool."""
    if not jobs:
        return {}
    board = ray.remote(num_cpus=0)(_Attempts).remote()
    task = ray.remote(_attempt).options(
        num_cpus=backend.threads, num_gpus=backend.gpus, max_retries=backend.max_retries, retry_exceptions=[RunKilled]
    )
    status = StatusLines(len(jobs), desc, progress)
    pending = {task.remote(board, name, fn, args): name for name, fn, args in jobs}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_S)
        for name, attempt, where in ray.get(board.drain.remote()):
            if attempt > 1:
                status.retried(name, attempt, where)
        for ref in ready:
            name = pending.pop(ref)
            try:
                status.record(name, True, ray.get(ref))
            except ray.exceptions.RayTaskError as err:  # the run itself failed: its own exception
                status.record(name, False, one_line(err.cause or err))
            except ray.exceptions.RayError as err:  # lost more times than it may be retried
                status.record(name, False, f"{one_line(err)[:300]} (after {backend.max_retries} retries)")
    return status.close()
