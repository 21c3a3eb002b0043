"""Fault injection (issue 17): a diverging optimiser, planning on a broken model, corrupt and mismatched
checkpoints, two runs on one directory, unwritable and full output locations, kill -9 at random moments.

Each test asserts the exit code, the one-line message and that no completed trial is lost."""

import subprocess
import sys
import time

import pytest

from tests.test_cli import ROOT, TINY, cli, error_lines, rows


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
