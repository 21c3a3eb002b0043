"""pets.compare --backend ray (issue 12), on a local Ray instance with this machine's CPUs.

Ground truth: the same comparison on the local backend (same seeds -> the same metrics and errors), the runs' own
metrics.csv and history.csv, and the operating system (a Ray worker killed with SIGKILL, its run's process gone).
Ray is in the dev extra: these tests run, never skip.
"""

import csv
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import ray

from pets.experiments.arguments import UsageError
from pets.experiments.cli import main
from pets.experiments.ray_backend import check_shared_storage
from pets.experiments.runner import ROOT
from pets.runs import rundir
from pets.tools.cli import EXIT_FAILED
from tests.processes import alive, children
from tests.test_compare import OFFLINE_ARGS, TINY

#: Wall-clock columns: the only ones that may differ between two runs with the same seed.
CLOCK = set(rundir.TIMING_COLUMNS)
ONLINE = ["online", "--envs", "invertedpendulum", "--models", "delta,gem", "--seeds", "0", "--trials", 2]
ONLINE += ["--preset", "fast", "--quiet", *TINY]
PLANNING = ("--planners", "--openloop-steps", "--openloop-episodes")  # with a value each; without --openloop: refused
OFFLINE = [
    a
    for i, a in enumerate(OFFLINE_ARGS)
    if a != "--openloop" and a not in PLANNING and OFFLINE_ARGS[i - 1] not in PLANNING
]
OFFLINE[OFFLINE.index("--seeds") + 1] = "0"  # one run per model: two tasks in parallel on two CPUs


def argv(args, out, *extra):
    return [str(a) for a in [*args, "--out", out, *extra]]


def metrics(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / rundir.METRICS_FILE, newline="") as f:
        return [{k: v for k, v in row.items() if k not in CLOCK} for row in csv.DictReader(f)]


def mtimes(out: Path) -> dict[str, int]:
    return {str(p.relative_to(out)): p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def online(tmp_path_factory):
    """The same online comparison on the local backend (2 workers) and on Ray; then the Ray one again."""
    base = tmp_path_factory.mktemp("ray-online")
    assert main(argv(ONLINE, base / "local", "--workers", 2)) == 0
    assert main(argv(ONLINE, base / "ray", "--backend", "ray")) == 0
    assert not ray.is_initialized()  # the sweep's own local instance is shut down
    return base


def test_online_ray_gives_the_local_backends_metrics(online):
    runs = sorted(p.name for p in (online / "local" / "runs").iterdir())
    assert runs == sorted(p.name for p in (online / "ray" / "runs").iterdir()) and len(runs) == 2
    for name in runs:
        local, remote = metrics(online / "local" / "runs" / name), metrics(online / "ray" / "runs" / name)
        assert len(local) == 2 and local == remote, name
    with open(online / "ray" / "summary.csv", newline="") as f:
        assert {r["model"] for r in csv.DictReader(f)} == {"delta", "gem"}


def test_rerun_of_a_finished_ray_sweep_does_no_new_work(online, capsys):
    out = online / "ray"
    before = mtimes(out / "runs")
    assert main(argv(ONLINE, out, "--backend", "ray")) == 0
    assert "2 runs: 2 reused, 0 to resume, 0 to start" in capsys.readouterr().err
    assert mtimes(out / "runs") == before and not ray.is_initialized()  # no run touched, Ray not even started


def test_offline_ray_gives_the_local_backends_errors(tmp_path):
    for backend in (["--backend", "local", "--workers", 2], ["--backend", "ray"]):
        assert main(argv(OFFLINE, tmp_path / backend[1], *backend)) == 0
    for name in ("invertedpendulum-delta-s0", "invertedpendulum-gem-s0"):
        local, remote = (json.loads((tmp_path / b / "runs" / name / "eval.json").read_text()) for b in ("local", "ray"))
        assert local["horizons"] == remote["horizons"] and local["start_points"] == remote["start_points"]
        assert local["horizons"]["5"]["mean_step_error"] > 0
        assert metrics(tmp_path / "local" / "runs" / name) == metrics(tmp_path / "ray" / "runs" / name)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_head(env: dict[str, str], log: Path, attempts: int = 3, wait_s: float = 240) -> subprocess.Popen:
    """``ray start --head --block``, returned once it prints that the runtime started. Ray gives its raylet a fixed
    30 s to register with the GCS; on 2 shared cores under the other test worker's load that start itself timed out
    once (CI, 2026-11-26: "Timed out while waiting for GCS", the head exited), so a head that exits during its
    start is started again, on fresh ports, up to ``attempts`` times; every attempt's output stays in ``log``."""
    for attempt in range(1, attempts + 1):
        gcs_port = free_port()
        ports = [f"--port={gcs_port}", f"--ray-client-server-port={free_port()}"]
        offset = log.stat().st_size if log.exists() else 0
        with open(log, "a") as f:
            f.write(f"--- ray start, attempt {attempt}\n")
            f.flush()
            head = subprocess.Popen(
                ["ray", "start", "--head", "--block", *ports, "--num-cpus=2", "--include-dashboard=false",
                 "--disable-usage-stats"],
                env=env, stdout=f, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip
        head.gcs_port = gcs_port  # what stop_head looks for in the address file the head leaves
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline and head.poll() is None:
            if "Ray runtime started" in log.read_text()[offset:]:
                return head
            time.sleep(1)
        stop_head(head)
    raise AssertionError(f"ray start --head did not start in {attempts} attempts:\n" + log.read_text()[-3000:])


def stop_head(head: subprocess.Popen) -> None:
    """Stop ``ray start --block`` as Ctrl-C in its terminal does: SIGINT to its group ends it in ~1.5 s, where
    SIGTERM took 32 s (Ray 2.60, 2026-12-01); SIGKILL if it is still there after 60 s. Then remove the address file
    it left for ``--address auto`` (Ray's temporary folder's ``ray_current_cluster``) if it still names this head:
    the machine keeps no pointer to a cluster that is gone."""
    if head.poll() is None:
        os.killpg(head.pid, signal.SIGINT)
    try:
        head.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(head.pid, signal.SIGKILL)
        head.wait()
    current = Path(os.environ.get("RAY_TMPDIR") or tempfile.gettempdir()) / "ray" / "ray_current_cluster"
    if current.is_file() and current.read_text().strip().endswith(f":{head.gcs_port}"):
        current.unlink()


def test_sweep_on_a_cluster_started_with_ray_start_gives_the_local_backends_metrics(online, tmp_path):
    """docs/cluster.md's path: ``ray start --head`` (in a shell with no Ray settings: Ray's own default auth mode,
    token auth since Ray 2.59), then ``pets.compare --address auto`` from another process on the head node."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    log = tmp_path / "ray-start.log"
    head = start_head(env, log)
    try:
        out = tmp_path / "cluster"
        cmd = [sys.executable, "-m", "pets.compare", *argv(ONLINE, out, "--backend", "ray", "--address", "auto")]
        # a hang (e.g. `auto` finding another cluster on this machine) fails here instead of stalling the suite
        done = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=600)
    finally:
        stop_head(head)
    assert done.returncode == 0, done.stderr[-1500:] + "\nray start: " + log.read_text()[-1500:]
    for name in sorted(p.name for p in (online / "local" / "runs").iterdir()):
        assert metrics(online / "local" / "runs" / name) == metrics(out / "runs" / name), name


#: The run the killed-worker tests kill: 5 trials, so that the kill after the first one leaves some to resume.
KILLED = ["online", "--envs", "invertedpendulum", "--models", "gem", "--seeds", "3", "--trials", 5]
KILLED += ["--preset", "fast", "--quiet", *TINY]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    """The killed run's ground truth, made once for both victims: the same run on the local backend, not killed."""
    out = tmp_path_factory.mktemp("ray-uninterrupted")
    assert main(argv(KILLED, out)) == 0
    return out / "runs" / "invertedpendulum-gem-s3"


@pytest.mark.parametrize("victim", ["worker", "run"])
def test_killed_ray_worker_run_resumes_from_its_checkpoint_with_the_same_metrics(victim, uninterrupted, tmp_path):
    """SIGKILL to the Ray worker running a run after its first trial, or to the run's own process (as the kernel's
    out-of-memory killer picks the process that holds the memory): Ray retries the task, the run resumes from its
    checkpoint (history.csv: start at 0, resume at >= 1 trials) and ends with the uninterrupted run's metrics."""
    out = tmp_path / "ray"
    driver = subprocess.Popen(
        [sys.executable, "-m", "pets.compare", *argv(KILLED, out, "--backend", "ray")],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    run_dir, log = out / "runs" / "invertedpendulum-gem-s3", out / "logs" / "invertedpendulum-gem-s3.log"
    # generous: the loop ends at the first trial; under load (the other xdist worker, other jobs) Ray's start and
    # the first trial took over 120 s once on 2 shared cores
    deadline, killed = time.monotonic() + 600, None
    while time.monotonic() < deadline and driver.poll() is None:
        if (run_dir / rundir.METRICS_FILE).is_file() and len(metrics(run_dir)) >= 1:
            worker = int(log.read_text().split(" pid ")[1].split(")")[0])
            run = children(worker)
            os.kill(worker if victim == "worker" else run[0], signal.SIGKILL)
            killed = (worker, run)
            break
        time.sleep(0.02)
    if killed is None and driver.poll() is None:
        driver.kill()
    stdout, stderr = driver.communicate(timeout=600)
    assert killed is not None, f"no first trial to kill in time, or the run ended first: {stderr[-2000:]}"
    assert driver.returncode == 0, stderr[-2000:]
    assert "invertedpendulum-gem-s3 retried (attempt 2" in stderr
    worker, run = killed
    assert run and not any(alive(pid) for pid in run)  # the run's own process died with its worker
    history = rundir.read_history(run_dir)
    assert [h["action"] for h in history] == ["start", "resume"]
    assert history[0]["trials_done"] == "0" and 1 <= int(history[1]["trials_done"]) < 5  # resumed, not restarted
    assert metrics(run_dir) == metrics(uninterrupted)
    assert len(metrics(run_dir)) == 5 and "# Online comparison" in stdout


@pytest.mark.parametrize(
    "extra, fragment",
    [
        (["--backend", "ray", "--workers", "2"], "--workers is for --backend local"),
        (["--address", "auto"], "--address is for --backend ray"),
        (["--max-retries", "5"], "--max-retries is for --backend ray"),
        (["--backend", "ray", "--threads", "64"], "every run asks for 64 CPU(s) and 0 GPU(s), but the largest"),
        (["--backend", "ray", "--threads", "0"], "--threads must be >= 1"),
    ],
)
def test_ray_usage_errors_are_one_line_exit_2(extra, fragment, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv(ONLINE, tmp_path, *extra))
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and fragment in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "runs").exists()


def test_storage_check_names_the_node_that_cannot_write_out():
    ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        with pytest.raises(UsageError, match=r"--out /proc/gem-pets is not writable from node .* shared file system"):
            check_shared_storage(ray, Path("/proc/gem-pets"))
    finally:
        ray.shutdown()


def test_a_private_instance_runs_its_workers_at_the_drivers_priority(monkeypatch):
    """Ray's own default starts workers at niceness 15, where beside any busy process a run gets a sliver of a core
    (docs/cluster.md); the instance a sweep starts for itself runs them at the driver's niceness."""
    from pets.experiments.backend import Backend
    from pets.experiments.ray_backend import connect

    monkeypatch.setenv("RAY_worker_niceness", "15")
    monkeypatch.delenv("RAY_worker_niceness")  # unset now, and unset again after the test
    ray_module = connect(Backend(kind="ray"))
    try:
        niceness = ray_module.remote(num_cpus=0)(lambda: os.nice(0))
        assert ray_module.get(niceness.remote()) == os.nice(0)
    finally:
        ray_module.shutdown()


def test_a_run_that_fails_by_itself_is_reported_with_its_reason_not_retried(tmp_path, capsys):
    """A run directory with a corrupt checkpoint: its resume exits 2; the task fails once (no retry: only lost
    workers are retried), the driver prints the reason, the summary lists the run, exit status EXIT_FAILED (3)."""
    from pets.config import make_config

    broken = tmp_path / "runs" / "invertedpendulum-delta-s9"
    broken.mkdir(parents=True)
    overrides = dict(item.split("=") for item in TINY)
    cfg = make_config("invertedpendulum", "delta", "fast", {**overrides, "seed": 9, "trials": 1, "threads": 1})
    rundir.write_config(broken, cfg)
    (broken / "checkpoint.pt").write_bytes(b"not a checkpoint")
    args = ["online", "--envs", "invertedpendulum", "--models", "delta", "--seeds", "9", "--trials", 1]
    assert main(argv([*args, "--preset", "fast", *TINY], tmp_path, "--backend", "ray")) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "invertedpendulum-delta-s9 failed: RuntimeError: exit 2; log" in err
    assert "is not a readable checkpoint" in err
    assert "retried" not in err
    assert len(Path(tmp_path / "logs" / "invertedpendulum-delta-s9.log").read_text().split("--resume")) == 2  # once
    assert "failed: RuntimeError: exit 2" in (tmp_path / "summary.md").read_text()


def test_a_users_own_env_module_imports_in_the_ray_workers(tmp_path):
    """``pets.compare online --envs mypend:SPEC --backend ray`` from the folder holding mypend.py (issue 55): the
    workers start elsewhere and still import it, as the local backend's child processes do."""
    from tests.test_own_env import SPEC_MODULE, _command

    me = tmp_path / "me"
    me.mkdir()
    (me / "mypend.py").write_text(SPEC_MODULE)
    (me / "tests").symlink_to(ROOT / "tests")  # the module builds on tests/custom_envs.py
    args = ["pets.compare", "online", "--envs", "mypend:SPEC", "--models", "delta", "--seeds", "0", "--trials", "1"]
    proc = _command(
        [*args, "--preset", "fast", "--quiet", *TINY, "--backend", "ray", "--out", "sweep"], me, module=True
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    (run,) = (me / "sweep" / "runs").iterdir()
    assert run.name.startswith("pendulum-delta-s0") and len(metrics(run)) == 1
