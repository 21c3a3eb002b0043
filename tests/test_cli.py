"""The real CLI end to end: a short run, its run directory, resume (also after kill -9), errors."""

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.tiny import TINY_MODEL, TINY_PLANNER

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "--preset",
    "fast",
    *TINY_PLANNER,
    *TINY_MODEL,
    "episode_length=30",
    "seed_steps=100",
    "threads=1",
    "--quiet",
]


def cli(*args, check=True, timeout=300):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "run_pets.py"), *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


def error_lines(stderr: str) -> list[str]:
    """The non-empty stderr lines besides the 'run directory:' notice (an error must be exactly one)."""
    return [line for line in stderr.splitlines() if line.strip() and not line.startswith("run directory:")]


def rows(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_smoke_two_trials_invertedpendulum(tmp_path):
    out = tmp_path / "run"
    cli("--model", "delta", "--env", "invertedpendulum", "--trials", 2, "--seed", 3, "--out", out, *TINY)
    for name in ("config.yaml", "metrics.csv", "checkpoint.pt", "rewards.png"):
        assert (out / name).is_file(), name
    metrics = rows(out)
    assert [int(r["trial"]) for r in metrics] == [0, 1]
    for col in (
        "trial",
        "env_steps",
        "episode_reward",
        "episode_length",
        "model_train_loss",
        "model_val_loss",
        "wall_time_s",
    ):
        assert col in metrics[0]
    seed_steps = 100
    assert int(metrics[0]["env_steps"]) == seed_steps + int(metrics[0]["episode_length"])
    assert int(metrics[1]["env_steps"]) == int(metrics[0]["env_steps"]) + int(metrics[1]["episode_length"])
    assert all(float(r["episode_reward"]) >= 1 for r in metrics)
    assert "planner:" in (out / "config.yaml").read_text() and "seed: 3" in (out / "config.yaml").read_text()


def test_same_seed_same_metrics(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        cli("--env", "invertedpendulum", "--trials", 3, "--seed", 5, "--out", out, *TINY)

    def key(rs):
        return [(r["episode_reward"], r["episode_length"], r["model_train_loss"]) for r in rs]

    assert key(rows(a)) == key(rows(b))


def test_resume_after_kill_matches_uninterrupted_run(tmp_path):
    ref, killed = tmp_path / "ref", tmp_path / "killed"
    args = ["--env", "invertedpendulum", "--trials", 4, "--seed", 11, *TINY]
    cli(*args, "--out", ref)
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "run_pets.py"), *map(str, args), "--out", str(killed)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 240
    while time.time() < deadline and not (killed / "metrics.csv").exists():
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done_before = len(rows(killed)) if (killed / "metrics.csv").exists() else 0
    assert done_before < 4, "the run finished before it could be killed; make it longer"
    cli("--resume", killed)
    got, want = rows(killed), rows(ref)
    assert [int(r["trial"]) for r in got] == [0, 1, 2, 3]
    assert [r["episode_reward"] for r in got] == [r["episode_reward"] for r in want]


def test_resume_can_extend_a_finished_run(tmp_path):
    out = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--out", out, *TINY)
    cli("--resume", out, "--trials", 2)
    assert [int(r["trial"]) for r in rows(out)] == [0, 1]


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--env", "pong"], "invertedpendulum"),
        (["--env", "hopper", "--model", "transformer"], "delta"),
        (["--env", "hopper", "planner.popsize=3"], "planner.population"),
        (["--env", "hopper", "trials=abc"], "trials"),
        (["--model", "delta"], "--env is required"),
        (["--resume", "/nonexistent/run"], "not a run directory"),
    ],
)
def test_bad_input_exits_2_with_one_line(args, fragment):
    proc = cli(*args, check=False, timeout=60)
    assert proc.returncode == 2
    lines = error_lines(proc.stderr)
    assert len(lines) == 1, proc.stderr
    assert fragment in lines[0]


def test_existing_run_directory_is_not_overwritten(tmp_path):
    out = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--out", out, *TINY)
    proc = cli("--env", "invertedpendulum", "--trials", 1, "--out", out, *TINY, check=False)
    assert proc.returncode == 2 and "--resume" in proc.stderr


@pytest.mark.parametrize("env", ["walker2d", "ant", "humanoid"])
def test_online_training_selects_a_trained_model(tmp_path, env):
    """Issue 18: after every trial's training the selected model is a trained one."""
    out = tmp_path / env
    changed = {
        "model.max_epochs=2": "model.max_epochs=10",
        "model.hidden_size=32": "model.hidden_size=64",
        "seed_steps=100": "seed_steps=400",
    }
    cli("--model", "gem", "--env", env, "--trials", 2, "--seed", 0, "--out", out, *[changed.get(a, a) for a in TINY])
    for row in rows(out):
        # training starts from the previous model (the seed data's, for trial 0) and improves on it; the
        # untrained network scores about 1 on this criterion (pets.onestep), "no change" too
        assert float(row["model_val_loss"]) < min(0.8, float(row["model_val_loss_initial"])), row


@pytest.mark.parametrize("holdout", ["0.1", "0"])
def test_diverging_training_stops_the_run_with_one_line(tmp_path, holdout):
    """Issue 17 item 1: a NaN model is never planned with; the run stops with exit 3 and says why."""
    out = tmp_path / "run"
    proc = cli(
        "--env",
        "reacher",
        "--model",
        "gem",
        "--out",
        out,
        *TINY,
        "model.lr=1000",
        f"model.holdout_ratio={holdout}",
        check=False,
    )
    lines = error_lines(proc.stderr)
    assert proc.returncode == 3, proc.stderr
    assert (
        len(lines) == 1 and "model training diverged in epoch" in lines[0] and "lower model.lr (now 1000)" in lines[0]
    )
    assert not (out / "checkpoint.pt").exists()  # nothing trained on a NaN model was saved


def test_planning_with_no_finite_return_stops_the_run_with_one_line(tmp_path, monkeypatch, capsys):
    """Issue 17 item 1: a model that predicts nothing finite (here: NaN weights after the second training, i.e.
    after trial 0) makes planning fail with exit 3 and one line naming trial and step; trial 0 is kept."""
    import torch

    import run_pets
    from pets import loop

    real_train, trainings = loop.PETSRun._train, {"n": 0}

    def train_then_break(self):
        real_train(self)
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
    assert "the run directory keeps the trials completed before this one" in err[0]
    assert [int(r["trial"]) for r in rows(out)] == [0]


def test_planning_with_a_broken_model_is_one_line_in_collect_and_openloop(tmp_path, capsys):
    """Issue 17 item 1: pets.collect --policy run:DIR and pets.openloop plan with a run's model; a model whose
    weights are NaN makes them exit 3 with one line (not a traceback), and collect writes nothing."""
    import torch

    import run_pets
    from pets import collect, openloop, rundir

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


def test_the_bar_over_trials_knows_its_total_and_shows_rate_and_eta(tmp_path, monkeypatch, capsys):
    """Issue 17 item 6: the trial-level bar is created with total=trials (initial=trials done on resume), so
    tqdm shows n/total, the rate and the remaining time."""
    import re

    import run_pets
    from pets import loop

    created = []

    class Recording(loop.tqdm):
        def __init__(self, *args, **kwargs):
            created.append(kwargs)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(loop, "tqdm", Recording)
    out = tmp_path / "run"
    visible = [a for a in TINY if a != "--quiet"]
    assert run_pets.main(["--env", "invertedpendulum", "--trials", "1", "--out", str(out), *visible]) == 0
    assert run_pets.main(["--resume", str(out), "--trials", "2"]) == 0
    bars = [(kw["total"], kw["initial"]) for kw in created if kw.get("unit") == "trial"]
    assert bars == [(1, 0), (2, 1)]
    err = capsys.readouterr().err.replace("\r", "\n")
    # e.g. "invertedpendulum-delta: 100%|##########| 2/2 [00:00<00:00,  1.63trial/s, reward=8.0, steps=41]"
    assert re.search(r"invertedpendulum-delta: +100%.* 2/2 \[\d\d:\d\d<\d\d:\d\d, +[\d.]+(trial/s|s/trial)", err), err


def test_overrides_are_accepted_anywhere_on_the_command_line():
    """Issue 17 item 5: key=value after an option used to be 'unrecognized arguments'."""
    proc = cli("--env", "reacher", "threads=1", "--preset", "fast", "planner.population=50", "--trials", 0, check=False)
    assert proc.returncode == 2 and "trials must be >= 1, got 0" in proc.stderr  # parsed through to the config check
    assert "unrecognized arguments" not in proc.stderr


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
        "edited-config": (good, "does not match config.yaml"),
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


def test_a_second_run_on_the_same_directory_is_refused_and_the_first_is_intact(tmp_path):
    """Issue 17 item 2: two runs with one --out used to both exit 0, one run's results silently lost."""
    out = tmp_path / "run"
    args = [sys.executable, str(ROOT / "run_pets.py"), "--env", "invertedpendulum", "--trials", 40, "--seed", 4]
    first = subprocess.Popen([*map(str, args), "--out", str(out), *TINY], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (out / "config.yaml").exists() and time.time() < deadline and first.poll() is None:
        time.sleep(0.05)
    for second_args in (["--out", out], ["--resume", out]):
        proc = (
            cli(*args[2:], *second_args, *TINY, check=False)
            if second_args[0] == "--out"
            else cli("--resume", out, check=False)
        )
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert "in use by another run" in lines[0] or "already holds a run" in lines[0], lines[0]
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert [int(r["trial"]) for r in rows(out)] == list(range(40))
    assert not list(out.glob(".*.tmp"))  # no temporary file left behind


def test_unwritable_output_locations_are_one_line_before_any_work(tmp_path):
    """Issue 17 item 4: an existing file in place of a directory, or a path under /proc, is refused up front."""
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    commands = [
        [str(ROOT / "run_pets.py"), "--env", "reacher", "--out", a_file / "run"],
        [str(ROOT / "run_pets.py"), "--env", "reacher", "--out", "/proc/gem-pets-test"],
        ["-m", "pets.collect", "--env", "reacher", "--policy", "random", "--episodes", 1, "--out", a_file / "d.npz"],
    ]
    for args in commands:
        proc = subprocess.run([sys.executable, *map(str, args)], cwd=ROOT, capture_output=True, text=True, timeout=120)
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1 and "not a writable directory" in lines[0], proc.stderr


def test_a_full_disk_during_a_run_is_one_line_and_keeps_the_completed_trials(tmp_path, monkeypatch, capsys):
    """Issue 17 item 4: ENOSPC while writing trial 1's checkpoint -> exit 3, one line; trial 0 survives and
    --resume finishes the run."""
    import errno

    import run_pets
    from pets import rundir

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


def test_resume_of_a_finished_run_regenerates_its_missing_artefacts(tmp_path):
    """Issue 17 item 6: a run killed right after its last checkpoint never got rewards.png, and --resume of a
    finished run printed done without regenerating it."""
    out = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--seed", 6, "--out", out, *TINY)
    (out / "rewards.png").unlink()
    (out / "metrics.csv").unlink()
    proc = cli("--resume", out)
    assert "done: 1 trials" in proc.stdout
    assert (out / "rewards.png").stat().st_size > 0 and [int(r["trial"]) for r in rows(out)] == [0]


def test_a_file_that_is_not_an_npz_archive_is_named_as_such(tmp_path):
    """Issue 17 item 6: numpy calls any non-zip file 'pickled (object) data'."""
    from pets.datasets import load_dataset

    for content in (b"hello\n", bytes(range(256))):
        path = tmp_path / "data.npz"
        path.write_bytes(content)
        with pytest.raises(ValueError, match=r"is not an \.npz archive; data sets are written by pets\.collect"):
            load_dataset(path)


def test_atomic_writes_keep_the_usual_file_mode(tmp_path):
    """Atomic writes go through mkstemp (0600); the result must be as readable as a file written with open()."""
    from pets.fileio import atomic_write_bytes

    atomic_write_bytes(tmp_path / "a.txt", b"x")
    (tmp_path / "b.txt").write_bytes(b"x")
    assert (tmp_path / "a.txt").stat().st_mode == (tmp_path / "b.txt").stat().st_mode
