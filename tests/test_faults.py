"""Fault injection (issue 17): a diverging optimiser, planning on a broken model, corrupt and mismatched
checkpoints, two runs on one directory, unwritable and full output locations, kill -9 at random moments.

Each test asserts the exit code, the one-line message and that no completed trial is lost."""

import functools
import math
import os
import random
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from pets.runs import rundir
from tests import warm
from tests.processes import collect_random, cpu_seconds, default_sigint
from tests.test_cli import ROOT, TINY, cli, error_lines, rows

#: The run the kill -9, full-disk and read-only tests interrupt: 6 short trials (a few seconds).
RUN_ARGS = ["--env", "invertedpendulum", "--trials", "6", "--seed", "7", *TINY]
#: Columns that measure time, not what the run computed.
TIMING = rundir.TIMING_COLUMNS


def computed(run_dir: Path) -> list[dict[str, str]]:
    """metrics.csv without the timing columns (what must be identical to an uninterrupted run)."""
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows(run_dir)]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted run of RUN_ARGS; the file ``seconds`` beside it says how long the command took."""
    out = tmp_path_factory.mktemp("reference") / "run"
    started = time.perf_counter()
    cli(*RUN_ARGS, "--out", out)
    (out.parent / "seconds").write_text(str(time.perf_counter() - started))
    return out


@pytest.fixture(scope="module")
def invertedpendulum_data(tmp_path_factory) -> Path:
    """A small invertedpendulum data set (3 random episodes)."""
    return collect_random(tmp_path_factory.mktemp("data") / "ip.npz", 3)


@pytest.mark.parametrize("holdout", ["0.1", "0"])
def test_diverging_training_stops_the_run_with_one_line(tmp_path, holdout):
    """Issue 17 item 1: a NaN model is never planned with; the run stops with exit 3 and says why."""
    out = tmp_path / "run"
    proc = cli(
        "--env",
        "reacher",
        "--model",
        "gem",
        "--trials",
        "1",
        "--out",
        out,
        *TINY,
        "model.lr=1000",
        f"model.holdout_ratio={holdout}",
        check=False,
    )
    lines = error_lines(proc.stderr)
    assert proc.returncode == 3, proc.stderr
    assert len(lines) == 1 and "lower model.lr (now 1000)" in lines[0]
    assert "training on the seed data before trial 0: model training diverged in epoch" in lines[0]
    assert lines[0].endswith("; no trial was completed")
    assert not (out / "checkpoint.pt").exists()  # nothing trained on a NaN model was saved


def test_planning_with_no_finite_return_stops_the_run_with_one_line(tmp_path, monkeypatch, capsys):
    """Issue 17 item 1: a model that predicts nothing finite (here: NaN weights after the second training, i.e.
    after trial 0) makes planning fail with exit 3 and one line naming trial and step; trial 0 is kept."""
    import torch

    import run_pets
    from pets import loop

    real_train, trainings = loop.PETSRun._train, {"n": 0}

    def train_then_break(self, when=None):
        real_train(self, when)
        trainings["n"] += 1
        if trainings["n"] == 2:  # seed data, trial 0, then break the model
            with torch.no_grad():
                for p in self.model.parameters():
                    p.fill_(float("nan"))

    monkeypatch.setattr(loop.PETSRun, "_train", train_then_break)
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        run_pets.main(["--env", "invertedpendulum", "--trials", "2", "--out", str(out), *TINY])
    err = error_lines(capsys.readouterr().err)
    assert exc.value.code == 3 and len(err) == 1, err
    assert "trial 1, step 0: planning failed: every candidate action sequence got a non-finite return" in err[0]
    assert "the trials completed before it are kept in" in err[0]
    assert [int(r["trial"]) for r in rows(out)] == [0]


def test_planning_with_a_broken_model_is_one_line_in_collect_and_openloop(tmp_path, capsys):
    """Issue 17 item 1: pets.collect --policy run:DIR and pets.openloop plan with a run's model; a model whose
    weights are NaN makes them exit 3 with one line (not a traceback), and collect writes nothing."""
    import torch

    import run_pets
    from pets import collect, openloop
    from pets.runs import rundir

    run = tmp_path / "run"
    run_pets.main(["--env", "invertedpendulum", "--trials", "1", "--out", str(run), *TINY])
    state = rundir.load_checkpoint(run)
    state["model"] = {k: v.fill_(float("nan")) if "weight" in k else v for k, v in state["model"].items()}
    rundir.save_checkpoint(run, state)
    capsys.readouterr()
    for main, args in (
        (collect.main, ["--policy", f"run:{run}", "--episodes", "1", "--out", str(tmp_path / "x.npz"), "--quiet"]),
        (openloop.main, ["--run", str(run), "--planner", "cem", "--steps", "5", "--episodes", "1", "--quiet"]),
    ):
        with pytest.raises(SystemExit) as exc:
            main(args)
        err = error_lines(capsys.readouterr().err)
        assert exc.value.code == 3 and len(err) == 1, err
        assert "planning failed: every candidate action sequence got a non-finite return" in err[0]
    assert not (tmp_path / "x.npz").exists()
    assert torch.isnan(rundir.load_checkpoint(run)["model"]["network.weights.0"]).all()


def test_corrupt_or_mismatched_checkpoint_is_one_line_on_resume(tmp_path):
    """Issue 17 item 3: a truncated, random, empty or foreign checkpoint, or a config.yaml edited after the run
    started, is one line with exit 2 on --resume (was a 21-line traceback)."""
    import shutil

    import torch

    ref = tmp_path / "ref"
    cli("--env", "invertedpendulum", "--trials", 1, "--seed", 2, "--out", ref, *TINY)
    good = (ref / "checkpoint.pt").read_bytes()
    cases = {
        "truncated": (good[: len(good) // 2], "is not a readable checkpoint"),
        "random": (bytes(range(256)) * 40, "is not a readable checkpoint"),
        "empty": (b"", "is not a readable checkpoint"),
        "foreign": (None, "is not a complete run checkpoint"),
        "edited-config": (
            good,
            "was edited after the run started (model.hidden_size: 32 in the checkpoint, 48 in config.yaml",
        ),
    }
    for name, (content, fragment) in cases.items():
        run = tmp_path / name
        shutil.copytree(ref, run)
        if name == "foreign":
            torch.save({"weights": torch.zeros(3)}, run / "checkpoint.pt")
        else:
            (run / "checkpoint.pt").write_bytes(content)
        if name == "edited-config":
            text = (run / "config.yaml").read_text()
            (run / "config.yaml").write_text(text.replace("hidden_size: 32", "hidden_size: 48"))
        proc = cli("--resume", run, "--trials", 2, check=False)
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], (name, proc.stderr)


def test_an_edited_setting_or_a_nan_in_the_buffer_is_one_line_on_resume_and_the_run_is_untouched(tmp_path):
    """Issue 34: a config.yaml whose model.lr was edited after the start was resumed with the checkpoint's lr while
    config.yaml claimed the edit (exit 0); a NaN in the checkpoint's replay buffer was a traceback from training.
    Both are now one line, exit 2, before any trial; --trials alone may change, and the untouched run resumes."""
    import shutil

    import torch

    ref = tmp_path / "ref"
    cli("--env", "invertedpendulum", "--trials", 1, "--seed", 2, "--out", ref, *TINY)
    edited, nan = tmp_path / "edited", tmp_path / "nan"
    shutil.copytree(ref, edited)
    text = (edited / "config.yaml").read_text()
    assert "  lr: 0.001\n" in text
    (edited / "config.yaml").write_text(text.replace("  lr: 0.001\n", "  lr: 0.002\n"))
    shutil.copytree(ref, nan)
    state = torch.load(nan / "checkpoint.pt", weights_only=False)
    state["buffer"]["next_obs"][5, 2] = float("nan")
    torch.save(state, nan / "checkpoint.pt")
    for run, fragment in (
        (edited, "was edited after the run started (model.lr: 0.001 in the checkpoint, 0.002 in config.yaml"),
        (nan, "holds non-finite values (NaN or inf) in its replay buffer (next_obs)"),
    ):
        before = (run / "metrics.csv").read_text()
        proc = cli("--resume", run, "--trials", 2, check=False)
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], proc.stderr
        assert (run / "metrics.csv").read_text() == before
    assert cli("--resume", ref, "--trials", 2, check=False).returncode == 0
    assert len(rows(ref)) == 2


def _interrupt(argv: list[str], under_way, timeout: float = 600.0) -> subprocess.CompletedProcess:
    """Run ``python -m ARGV``, send it SIGINT once ``under_way(pid)`` says its work has begun, return its result.
    The child is killed on any failure, so a failing test never leaves it running (on a loaded machine its CPU
    time grows slowly: the wait is long, and a child that never got under way fails the test, uninterrupted)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", *argv], cwd=ROOT, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint
    )
    try:
        deadline = time.monotonic() + timeout
        while not under_way(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert proc.poll() is None, "the command ended before it could be interrupted"
        assert under_way(proc.pid), f"the command's work had not begun after {timeout:.0f} s"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return subprocess.CompletedProcess(argv, proc.returncode, "", err)


def test_ctrl_c_in_collect_and_train_is_one_line_and_exit_130(tmp_path, invertedpendulum_data):
    """Issue 34: Ctrl-C in pets.collect and pets.train was exit 130 with a KeyboardInterrupt traceback; now one line
    that says nothing was written, and nothing is."""
    out = tmp_path / "data.npz"
    # Collecting once the process has spent more CPU time than its imports take (~3 s).
    proc = _interrupt(
        [
            "pets.collect",
            "--env",
            "ant",
            "--policy",
            "random",
            "--episodes",
            "100000",
            "--threads",
            "1",
            "--out",
            str(out),
            "--quiet",
        ],
        lambda pid: cpu_seconds(pid) > 8.0,
    )
    lines = error_lines(proc.stderr)
    assert proc.returncode == 130 and len(lines) == 1 and "pets.collect: interrupted; nothing was written" in lines[0]
    assert "Traceback" not in proc.stderr and not out.exists()
    run = tmp_path / "run"
    proc = _interrupt(
        [
            "pets.train",
            "--data",
            str(invertedpendulum_data),
            "--model",
            "delta",
            "--out",
            str(run),
            "--epochs",
            "100000",
            "--quiet",
            "threads=1",
            "model.patience=100000",
        ],
        lambda pid: (run / ".lock").exists() and cpu_seconds(pid) > 1.0,  # the lock: training has begun
    )
    lines = error_lines(proc.stderr)
    assert proc.returncode == 130 and len(lines) == 1 and "pets.train: interrupted; no run was written" in lines[0]
    assert "Traceback" not in proc.stderr and not (run / "config.yaml").exists()


def test_train_on_a_data_set_of_other_widths_is_one_line_naming_the_file_and_field(tmp_path, invertedpendulum_data):
    """Issue 34: an .npz whose obs width does not match its env field was a traceback from training; now one line
    (exit 2) naming the file, the field, what was found and what the env needs, before any directory is made."""
    import numpy as np

    data = dict(np.load(invertedpendulum_data))
    data["obs"] = data["obs"][..., :3]
    bad = tmp_path / "narrow.npz"
    np.savez(bad, **data)
    proc = warm.run(
        [sys.executable, "-m", "pets.train", "--data", str(bad), "--model", "delta", "--out", str(tmp_path / "run")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert f"{bad}: its 'obs' entries are 3 wide, but invertedpendulum (its 'env' field) has obs_dim 4" in lines[0]
    assert not (tmp_path / "run").exists()


def test_a_setting_given_twice_or_bad_elites_is_one_line_and_leaves_no_directory(tmp_path):
    """Issue 34: `--trials 2 trials=1` silently took the flag; planner.elites=0 (or above the population) was a
    traceback from the planner after the run directory was made. Both are one line, exit 2, nothing on disk."""
    for extra, fragment in (
        (["--trials", 2, "trials=1"], "give trials once: --trials 2 or trials=1, not both"),
        (["--model", "gem", "head=delta"], "give head once: --model gem or head=delta, not both"),
        (["env=hopper"], "give env once: --env reacher or env=hopper, not both"),  # was hopper, silently
        (["planner.elites=0"], "planner.elites must be a ratio in (0, 1) of the population or a whole count"),
        (["planner.elites=1000"], "whole count in [1, planner.population=16], got 1000"),
    ):
        out = tmp_path / "run"
        proc = cli("--env", "reacher", "--out", out, *TINY, *extra, check=False)
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], (extra, proc.stderr)
        assert not out.exists()


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="checks the refusal where torch sees no CUDA")
def test_cuda_where_there_is_none_is_refused_before_the_run_directory_is_made(tmp_path):
    out = tmp_path / "run"
    proc = cli("--env", "reacher", "--out", out, "--device", "cuda", *TINY, check=False)
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and "torch sees no CUDA device" in lines[0]
    assert not out.exists()


def test_a_second_run_on_the_same_directory_is_refused_and_the_first_is_intact(tmp_path):
    """Issue 17 item 2: two runs with one --out used to both exit 0, one run's results silently lost. The first run
    is stopped (SIGSTOP) while the second tries, so it cannot end before the second has been refused."""
    out = tmp_path / "run"
    args = [sys.executable, str(ROOT / "run_pets.py"), "--env", "invertedpendulum", "--trials", 8, "--seed", 4]
    first = subprocess.Popen([*map(str, args), "--out", str(out), *TINY], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (out / "config.yaml").exists() and time.time() < deadline and first.poll() is None:
        time.sleep(0.05)
    first.send_signal(signal.SIGSTOP)
    try:
        refusals = [
            cli(*args[2:], "--out", out, *TINY, check=False),
            cli("--resume", out, check=False),
        ]
    finally:
        first.send_signal(signal.SIGCONT)
    for proc in refusals:
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert f"{out} is in use by another run (process {first.pid}); wait for it to finish" in lines[0], lines[0]
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert [int(r["trial"]) for r in rows(out)] == list(range(8))
    assert not list(out.glob(".*.tmp"))  # no temporary file left behind


def test_unwritable_output_locations_are_one_line_before_any_work(tmp_path, reference, invertedpendulum_data):
    """Issue 17 item 4: an existing file in place of a directory, a path under /proc, or a directory in place of
    a --json file is refused up front (exit 2, one line)."""
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    unwritable = "not a writable directory"
    commands = [
        ([str(ROOT / "run_pets.py"), "--env", "reacher", "--out", a_file / "run"], unwritable),
        ([str(ROOT / "run_pets.py"), "--env", "reacher", "--out", a_file], f"{a_file} is {unwritable} (File exists)"),
        ([str(ROOT / "run_pets.py"), "--env", "reacher", "--out", "/proc/gem-pets-test"], unwritable),
        (["-m", "pets.collect", "--env", "reacher", "--policy", "random", "--out", a_file / "d.npz"], unwritable),
        (["-m", "pets.train", "--data", invertedpendulum_data, "--model", "delta", "--out", a_file], unwritable),
        (
            ["-m", "pets.evaluate", "--run", reference, "--data", invertedpendulum_data, "--json", tmp_path],
            f"--json {tmp_path} is a directory; give a file name",
        ),
    ]
    for args, fragment in commands:
        proc = warm.run([sys.executable, *map(str, args)], cwd=ROOT, capture_output=True, text=True, timeout=120)
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], (args, proc.stderr)


def test_a_full_disk_during_a_run_is_one_line_and_keeps_the_completed_trials(tmp_path, monkeypatch, capsys):
    """Issue 17 item 4: ENOSPC while writing trial 1's checkpoint -> exit 3, one line; trial 0 survives and
    --resume finishes the run."""
    import errno

    import run_pets
    from pets.runs import rundir

    out = tmp_path / "run"
    real_write = rundir.atomic_write_bytes
    calls = {"checkpoints": 0}

    def full_disk(path, data):
        if path.name == "checkpoint.pt":
            calls["checkpoints"] += 1
            if calls["checkpoints"] == 2:
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real_write(path, data)

    monkeypatch.setattr(rundir, "atomic_write_bytes", full_disk)
    with pytest.raises(SystemExit) as exc:
        run_pets.main(["--env", "invertedpendulum", "--trials", "2", "--out", str(out), *TINY])
    err = error_lines(capsys.readouterr().err)
    assert exc.value.code == 3 and len(err) == 1 and "No space left on device" in err[0] and "--resume" in err[0]
    assert [int(r["trial"]) for r in rows(out)] == [0]
    monkeypatch.setattr(rundir, "atomic_write_bytes", real_write)
    cli("--resume", out)
    assert [int(r["trial"]) for r in rows(out)] == [0, 1]


def test_a_later_divergence_names_its_trial_and_keeps_the_trials_before(tmp_path, monkeypatch, capsys):
    """Issue 17 item 1: training that diverges in trial 1 (an absurd learning rate from then on) stops the run with
    exit 3 and one line naming trial 1; trial 0 stays in metrics.csv and the checkpoint, and --resume (with the
    configured learning rate again) finishes the run as if nothing had happened."""
    import run_pets
    from pets import loop
    from pets.runs import rundir

    real_train, trainings = loop.PETSRun._train, {"n": 0}

    def train_then_raise_lr(self, when=None):
        trainings["n"] += 1
        if trainings["n"] == 3:  # the seed data's training, trial 0's, then trial 1's
            self.trainer.lr = 1e30
            for group in self.trainer.optimizer.param_groups:
                group["lr"] = 1e30
        real_train(self, when)

    monkeypatch.setattr(loop.PETSRun, "_train", train_then_raise_lr)
    out = tmp_path / "run"
    args = [*RUN_ARGS]
    args[args.index("--trials") + 1] = "2"
    with pytest.raises(SystemExit) as exc:
        run_pets.main([*args, "--out", str(out)])
    err = error_lines(capsys.readouterr().err)
    assert exc.value.code == 3 and len(err) == 1, err
    assert "trial 1: model training diverged in epoch 1" in err[0] and "lower model.lr (now 1e+30)" in err[0]
    assert "the trials completed before it are kept in" in err[0]
    assert [int(r["trial"]) for r in rows(out)] == [0]
    assert rundir.load_checkpoint(out)["trials_done"] == 1
    monkeypatch.setattr(loop.PETSRun, "_train", real_train)
    assert run_pets.main(["--resume", str(out)]) == 0
    assert [int(r["trial"]) for r in rows(out)] == [0, 1]


def test_kill_9_at_random_moments_then_resume_gives_the_uninterrupted_metrics(tmp_path, reference):
    """Issue 17: kill -9 at five random moments, each time continued with --resume (or started again when it died
    before writing config.yaml), then finished: metrics.csv (timing aside) is identical to the uninterrupted run's.
    The first kill falls at a random time of a fresh start (imports, seed data, first training), the others at a
    random time after a random number of completed trials (in the next trial's training, planning or file
    writes). After every kill the completed trials are a prefix of the reference's and never fewer than before (no
    completed trial is lost)."""
    run = tmp_path / "run"
    whole = float((reference.parent / "seconds").read_text())  # how long one whole run takes here and now
    chooser = random.Random(17)
    plan = [(0, chooser.uniform(0.1, 0.5) * whole)]
    plan += [(after, chooser.uniform(0.0, 0.15) * whole) for after in sorted(chooser.sample(range(1, 6), 4))]

    def trials_done() -> int:
        return len(rows(run)) if (run / "metrics.csv").exists() else 0

    want, done, killed = computed(reference), 0, []
    for after, delay in plan:
        how = ["--resume", run] if (run / "config.yaml").exists() else [*RUN_ARGS, "--out", run]
        proc = subprocess.Popen(
            [sys.executable, str(ROOT / "run_pets.py"), *map(str, how)],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        deadline = time.time() + 240
        while proc.poll() is None and trials_done() < after and time.time() < deadline:
            time.sleep(0.02)
        try:
            proc.wait(timeout=delay)  # finished before its kill: the next resume has nothing left to do
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            killed.append((after, round(delay, 2)))
        got = computed(run) if (run / "metrics.csv").exists() else []
        assert got == want[: len(got)] and len(got) >= done, (plan, got)
        done = len(got)
    assert len(killed) >= 4, f"only the kills {killed} of {plan} hit a running process"
    proc = cli("--resume", run)
    assert "done: 6 trials" in proc.stdout
    assert computed(run) == want
    assert (run / "rewards.png").stat().st_size > 0 and not list(run.glob(".*.tmp"))


def start_stalled(name: str, nth: int, marker: Path, args: list) -> subprocess.Popen:
    """``run_pets.py ARGS`` under tests/stall_write.py, which stops the ``nth`` write of ``name`` halfway and
    creates ``marker``; returned once the write has stalled (or the run exited, or 240 s passed)."""
    command = [sys.executable, "-m", "tests.stall_write", name, str(nth), str(marker), str(ROOT / "run_pets.py")]
    proc = subprocess.Popen(
        [*command, *map(str, args)], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    deadline = time.time() + 240
    while not marker.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    return proc


def test_kill_9_inside_a_checkpoint_write_loses_nothing(tmp_path, reference):
    """Issue 17: kill -9 while trial 1's checkpoint is half written (tests/stall_write.py stops the real write
    halfway): checkpoint.pt still holds trial 0, metrics.csv lists trial 0, and --resume removes the half-written
    temporary file and finishes with the uninterrupted run's metrics."""
    from pets.runs import rundir

    run, marker = tmp_path / "run", tmp_path / "stalled"
    proc = start_stalled("checkpoint.pt", 2, marker, [*RUN_ARGS, "--out", run])
    assert marker.exists(), f"the write never stalled (exit {proc.poll()}): {proc.stderr.read() if proc.poll() else ''}"
    (partial,) = run.glob(".checkpoint.pt.*.tmp")
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 0 < partial.stat().st_size < (run / "checkpoint.pt").stat().st_size  # half of trial 1's checkpoint
    assert rundir.load_checkpoint(run)["trials_done"] == 1 and [int(r["trial"]) for r in rows(run)] == [0]
    cli("--resume", run)
    assert computed(run) == computed(reference)
    assert not partial.exists() and not list(run.glob(".*.tmp"))


@functools.cache
def mount_namespace() -> tuple[str, ...] | None:
    """A command prefix that runs its command in a private mount namespace where it may mount a tmpfs (``unshare``,
    as root or in a user namespace), or None where this system allows neither."""
    if shutil.which("unshare") is None:
        return None
    with tempfile.TemporaryDirectory() as probe:
        for prefix in (("unshare", "--mount", "--map-root-user"), ("unshare", "--mount")):
            mount = [*prefix, "sh", "-c", 'mount -t tmpfs -o size=64k tmpfs "$0" && touch "$0/x"', probe]
            if subprocess.run(mount, capture_output=True, timeout=30).returncode == 0:
                return prefix
    return None


def in_tmpfs(tmp_path: Path, commands: str) -> Path:
    """Run the shell ``commands`` in a private mount namespace (the host never sees its mounts) with ``$MNT`` an
    empty directory to mount a tmpfs on and ``$OUT`` a directory that outlives it; ``run NAME CMD ...`` records
    CMD's stdout, stderr and exit status as $OUT/NAME.{out,err,rc}. Returns $OUT. Skips the test where no mount
    namespace can be had (the ENOSPC mock test still covers a full disk there)."""
    prefix = mount_namespace()
    if prefix is None:
        pytest.skip("this system lets no process mount a tmpfs (no unshare; not root and no user namespaces)")
    mnt, out = tmp_path / "mnt", tmp_path / "out"
    mnt.mkdir()
    out.mkdir()
    script = f'set -u\nrun() {{ n=$1; shift; "$@" >"$OUT/$n.out" 2>"$OUT/$n.err"; echo $? >"$OUT/$n.rc"; }}\n{commands}'
    env = {**os.environ, "MNT": str(mnt), "OUT": str(out), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([*prefix, "sh", "-c", script], cwd=ROOT, env=env, capture_output=True, text=True, timeout=500)
    assert proc.returncode == 0, proc.stderr
    return out


def outcome(out: Path, name: str) -> tuple[int, list[str]]:
    """(exit status, error lines) of the command ``run NAME`` recorded in ``out``."""
    return int((out / f"{name}.rc").read_text()), error_lines((out / f"{name}.err").read_text())


def test_a_read_only_file_system_is_one_line_before_any_work(tmp_path, reference, invertedpendulum_data):
    """Issue 17 item 4: every command whose output lies on a read-only file system (a tmpfs mounted ro) exits 2
    with one line before any work (the collection of 100000 episodes and the 100000 trials never start), and writes
    nothing; a finished run on read-only media cannot be resumed in place either."""
    py, run_pets, data = shlex.quote(sys.executable), shlex.quote(str(ROOT / "run_pets.py")), invertedpendulum_data
    args = shlex.join([*RUN_ARGS[:2], "--trials", "100000", *RUN_ARGS[4:]])
    out = in_tmpfs(
        tmp_path,
        f"""
        mount -t tmpfs -o size=1m tmpfs "$MNT"
        cp -a {shlex.quote(str(reference))} "$MNT/run"
        mount -o remount,ro "$MNT"
        run run_pets {py} {run_pets} {args} --out "$MNT/new"
        run resume {py} {run_pets} --resume "$MNT/run" --trials 7 --quiet
        run train {py} -m pets.train --data {data} --model delta --out "$MNT/t" --quiet threads=1
        run collect {py} -m pets.collect --env invertedpendulum --policy random --episodes 100000 --out "$MNT/d.npz"
        run evaluate {py} -m pets.evaluate --run "$MNT/run" --data {data} --json "$MNT/e.json" --threads 1
        run openloop {py} -m pets.openloop --run "$MNT/run" --json "$MNT/o.json" --threads 1 --quiet
        ls -A "$MNT" "$MNT/run" >"$OUT/ls"
        """,
    )
    for name, fragment in (
        ("run_pets", "run_pets.py: error: {MNT}/new is not a writable directory (Read-only file system); pick another"),
        ("resume", "{MNT}/run is not a writable directory (Read-only file system); copy the run somewhere writable"),
        ("train", "pets.train: error: {MNT}/t is not a writable directory (Read-only file system); pick another --out"),
        ("collect", "pets.collect: error: cannot write --out {MNT}/d.npz: {MNT} is not a writable directory (Read-"),
        ("evaluate", "pets.evaluate: error: cannot write --json {MNT}/e.json: {MNT} is not a writable directory (Rea"),
        ("openloop", "pets.openloop: error: cannot write --json {MNT}/o.json: {MNT} is not a writable directory (Rea"),
    ):
        code, lines = outcome(out, name)
        assert code == 2 and len(lines) == 1 and fragment.format(MNT=tmp_path / "mnt") in lines[0], (name, lines)
    listing = (out / "ls").read_text().split()
    assert "new" not in listing and "t" not in listing and not any(n.endswith(".tmp") for n in listing), listing


def test_a_full_file_system_is_one_line_keeps_the_completed_trials_and_resume_finishes(
    tmp_path, reference, invertedpendulum_data
):
    """Issue 17 item 4: a run on a 200 kB tmpfs fills it while writing trial 1's checkpoint: exit 3, one line that
    names the file and says to free space and --resume; trial 0 is kept, no temporary file is left; after the tmpfs
    grows, --resume finishes with the uninterrupted run's metrics. On a full tmpfs pets.train, pets.collect and
    pets.evaluate --json exit 3 with one line too, and leave no partial file."""
    py, run_pets, data = shlex.quote(sys.executable), shlex.quote(str(ROOT / "run_pets.py")), invertedpendulum_data
    out = in_tmpfs(
        tmp_path,
        f"""
        mount -t tmpfs -o size=200k tmpfs "$MNT"
        run first {py} {run_pets} {shlex.join(RUN_ARGS)} --out "$MNT/run"
        cp -a "$MNT/run" "$OUT/failed"
        mount -o remount,size=8m "$MNT"
        run resume {py} {run_pets} --resume "$MNT/run" --quiet
        cp -a "$MNT/run" "$OUT/resumed"
        dd if=/dev/zero of="$MNT/fill" bs=4k 2>/dev/null
        run train {py} -m pets.train --data {data} --model delta --out "$MNT/t" --quiet threads=1 model.max_epochs=2
        run collect {py} -m pets.collect --env invertedpendulum --policy random --episodes 2 --out "$MNT/d.npz" \
            --threads 1 --quiet
        run evaluate {py} -m pets.evaluate --run "$MNT/run" --data {data} --json "$MNT/e.json" --threads 1 \
            --horizons 1,2 --starts 1
        ls -A "$MNT" "$MNT/t" >"$OUT/ls"
        """,
    )
    mnt = tmp_path / "mnt"
    code, lines = outcome(out, "first")
    assert code == 3 and len(lines) == 1, lines
    assert (
        f"run_pets.py: error: writing {mnt}/run/checkpoint.pt failed (No space left on device); the trials "
        f"completed before it are kept: free space, then --resume {mnt}/run" == lines[0]
    )
    failed = out / "failed"
    assert computed(failed) == computed(reference)[:1] and not list(failed.glob(".*.tmp"))
    assert outcome(out, "resume") == (0, [])
    assert computed(out / "resumed") == computed(reference)
    for name, fragment in (
        ("train", f"pets.train: error: writing {mnt}/t/checkpoint.pt failed (No space left on device); no run was"),
        ("collect", f"pets.collect: error: writing {mnt}/d.npz failed (No space left on device); nothing was writ"),
        ("evaluate", f"pets.evaluate: error: writing {mnt}/e.json failed (No space left on device); the results are"),
    ):
        code, lines = outcome(out, name)
        assert code == 3 and len(lines) == 1 and fragment in lines[0], (name, lines)
    assert "horizon" in (out / "evaluate.out").read_text()  # the results were printed before the write failed
    listing = (out / "ls").read_text().split()
    assert not {"d.npz", "e.json", "checkpoint.pt", "config.yaml"} & set(listing), listing
    assert not any(n.endswith(".tmp") for n in listing), listing


def test_a_start_that_failed_removes_the_directory_it_made_empty_or_holding_only_its_lock(tmp_path):
    """A run that stopped before writing anything (a Ctrl-C after the writability probe made ``--out``, before the
    lock was taken, left an empty folder on 2026-11-29) leaves no folder it made; a folder the user gave stays,
    and one holding anything else is left as it is."""
    from pets.runs.fileio import LOCK_FILE, remove_if_unused

    empty, lock_only, given, holding = (tmp_path / n for n in ("empty", "lock-only", "given", "holding"))
    for d in (empty, lock_only, given, holding):
        d.mkdir()
    for d in (lock_only, given, holding):
        (d / LOCK_FILE).touch()
    (holding / "config.yaml").write_text("env: reacher\n")
    for d, created in ((empty, True), (lock_only, True), (given, False), (holding, True)):
        remove_if_unused(d, created)
    assert not empty.exists() and not lock_only.exists()
    assert given.is_dir() and not any(given.iterdir())
    assert sorted(p.name for p in holding.iterdir()) == sorted([LOCK_FILE, "config.yaml"])


def test_a_second_offline_training_on_the_same_directory_is_refused(tmp_path, invertedpendulum_data):
    """Issue 17 item 2: pets.train holds the run directory's lock too; while another process holds it, a second
    training exits 2 with one line before any work and writes nothing."""
    from pets.runs.fileio import locked

    out = tmp_path / "run"
    with locked(out):
        proc = warm.run(
            [
                sys.executable,
                "-m",
                "pets.train",
                "--data",
                str(invertedpendulum_data),
                "--model",
                "delta",
                "--out",
                str(out),
                "--quiet",
                "threads=1",
                "model.max_epochs=2",
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert f"pets.train: error: {out} is in use by another run (process {os.getpid()}); wait for it" in lines[0]
    assert sorted(p.name for p in out.iterdir()) == [".lock"]


def test_an_empty_truncated_or_unparsable_config_is_one_line_on_resume(tmp_path, reference):
    """Issue 17 item 3: a config.yaml that is empty, cut short or not YAML is one line with exit 2 that says what
    to do (an empty one used to load the defaults and fail on a shape mismatch)."""
    text = (reference / "config.yaml").read_text()
    cases = {
        "empty": ("", "config.yaml is empty or not a YAML mapping; restore the config.yaml the run was started"),
        "truncated": (text[: text.index("planner:")], "config.yaml has no planner (truncated?); restore the config"),
        "not-yaml": ("env: [invertedpendulum\n  {{: x", "config.yaml is not a readable YAML file (while parsing"),
    }
    for name, (content, fragment) in cases.items():
        run = tmp_path / name
        shutil.copytree(reference, run)
        (run / "config.yaml").write_text(content)
        proc = cli("--resume", run, "--trials", 7, check=False)
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], (name, proc.stderr)
        assert [int(r["trial"]) for r in rows(run)] == list(range(6))  # the completed trials are untouched


def test_a_run_killed_while_writing_its_last_plot_gets_it_on_resume(tmp_path):
    """Issue 17 item 6: a run killed right after its last checkpoint (here: inside the write of rewards.png after
    the only trial) never got rewards.png; --resume of the finished run writes it and says done."""
    from pets.runs import rundir

    run, marker = tmp_path / "run", tmp_path / "stalled"
    args = [*RUN_ARGS]
    args[args.index("--trials") + 1] = "1"
    proc = start_stalled("rewards.png", 1, marker, [*args, "--out", run])
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert marker.exists() and not (run / "rewards.png").exists()
    assert rundir.load_checkpoint(run)["trials_done"] == 1
    assert "done: 1 trials" in cli("--resume", run).stdout
    assert (run / "rewards.png").stat().st_size > 0 and not list(run.glob(".*.tmp"))


def test_the_checkpoint_keeps_the_keys_of_before_the_parts_protocol_and_round_trips() -> None:
    """PETSRun's state is its parts' (``PETSRun.parts``): the checkpoint has the keys that runs written before wrote,
    with the value and the feedback law where the config has them, and loading it gives the same state back."""
    import torch

    from pets import loop
    from pets.config import make_config

    def same(a, b) -> bool:
        if isinstance(a, torch.Tensor):
            return torch.equal(a, b)
        if isinstance(a, dict):
            return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
        return bool((a == b).all()) if hasattr(a, "all") else a == b

    keys = "config trials_done env_steps wall_time_s rows cpu_time_s model trainer buffer train_gen plan_gen np_rng"
    keys += " torch_rng"
    keys = keys.split() + ["last_train"]
    for env, extra in (("invertedpendulum", ["value", "value_gen"]), ("inverteddoublependulum", ["feedback"])):
        cfg = make_config(env, preset="fast", overrides={"threads": 1, "model.hidden_size": 8})
        run = loop.PETSRun(cfg)
        run.trials_done, run.rows = 2, [{"trial": 0}, {"trial": 1}]
        torch.rand(3, generator=run.plan_gen, device=run.plan_gen.device)
        state = run.state_dict()
        assert list(state) == keys + extra
        other = loop.PETSRun(cfg)
        other.load_state_dict(state)
        assert same(other.state_dict(), state) and other.rows == run.rows
    del state["cpu_time_s"]  # a checkpoint written before the column: its CPU seconds are not known
    other.load_state_dict(state)
    assert math.isnan(other.cpu_time_s) and other.wall_time_s == run.wall_time_s


def test_metrics_written_before_the_cpu_column_read_back_with_nan(tmp_path) -> None:
    """A run resumed from a checkpoint of before ``cpu_time_s``: its old rows have no such key, written as nan (a
    float the readers parse), and the online statistics give no CPU minutes for it instead of failing."""
    from pets.experiments.studies.online import online_run_stats

    old = {"trial": 0, "env_steps": 10, "episode_reward": 5.0, "episode_length": 10, "wall_time_s": 3.0}
    new = {**old, "trial": 1, "env_steps": 20, "wall_time_s": 6.0, "cpu_time_s": math.nan}
    rundir.write_metrics(tmp_path, [old, new])
    read = rundir.read_metrics(tmp_path / rundir.METRICS_FILE)
    assert [math.isnan(r["cpu_time_s"]) for r in read] == [True, True] and read[1]["wall_time_s"] == 6.0
    stats = online_run_stats(read, 2, 1, threshold=4.0)
    assert stats["minutes_to_threshold"] == 3.0 / 60 and math.isnan(stats["cpu_minutes_to_threshold"])
    assert math.isnan(stats["cpu_time_s"])


def test_a_directory_in_the_way_of_a_runs_file_says_so_not_free_space(tmp_path: Path, capsys) -> None:
    """A run whose history.csv, diverged.txt or .lock was made a directory: --resume fails writing it, exit 3, in one
    line that names the directory in the way and says to move it (freeing space would not help); once it is moved,
    --resume finishes. A file in the way of a folder on a written path (ENOTDIR) is named the same way."""
    run = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--out", run, *TINY)
    for name in (rundir.HISTORY_FILE, rundir.DIVERGED_FILE, ".lock"):
        copy = tmp_path / f"run-{name.strip('.').replace('.', '-')}"
        shutil.copytree(run, copy)
        (copy / name).unlink(missing_ok=True)
        (copy / name).mkdir()
        proc = cli("--resume", copy, "--trials", 2, "--quiet", check=False)
        assert proc.returncode == 3 and error_lines(proc.stderr) == [
            f"run_pets.py: error: writing {copy / name} failed (Is a directory): it is a directory, not a file; the "
            f"trials completed before it are kept: move or delete that directory, then --resume {copy}"
        ], proc.stderr
    (copy / ".lock").rmdir()
    assert cli("--resume", copy, "--trials", 2, "--quiet").returncode == 0 and len(rows(copy)) == 2
    from pets.tools.cli import write_failed

    (tmp_path / "videos").write_text("a file\n")
    with pytest.raises(OSError) as failed:
        (tmp_path / "videos" / "trial-0000.mp4").write_bytes(b"")
    with pytest.raises(SystemExit) as exited:
        write_failed("run_pets.py", failed.value, "no trial was completed; free space, then start the run again")
    assert exited.value.code == 3 and capsys.readouterr().err == (
        f"run_pets.py: error: writing {tmp_path / 'videos' / 'trial-0000.mp4'} failed (Not a directory): "
        f"{tmp_path / 'videos'} is a file, not a folder; no trial was completed; move or delete that file, then start "
        "the run again\n"
    )
