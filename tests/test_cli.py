"""The real CLI end to end: a short run, its run directory, resume (also after kill -9), errors."""

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pets.runs import rundir
from tests import warm
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
    proc = warm.run(
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
        "cpu_time_s",
    ):
        assert col in metrics[0]
    cpu = [float(r["cpu_time_s"]) for r in metrics]
    assert 0 < cpu[0] < cpu[1]  # the process's CPU seconds, cumulative like wall_time_s
    seed_steps = 100
    assert int(metrics[0]["env_steps"]) == seed_steps + int(metrics[0]["episode_length"])
    assert int(metrics[1]["env_steps"]) == int(metrics[0]["env_steps"]) + int(metrics[1]["episode_length"])
    assert all(float(r["episode_reward"]) >= 1 for r in metrics)
    assert "planner:" in (out / "config.yaml").read_text() and "seed: 3" in (out / "config.yaml").read_text()


def test_same_seed_same_metrics(tmp_path):
    """Every column of metrics.csv but the timings (pets.runs.rundir.TIMING_COLUMNS) is the same bits."""
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        cli("--env", "invertedpendulum", "--trials", 3, "--seed", 5, "--out", out, *TINY)

    def key(rs):
        return [{k: v for k, v in r.items() if k not in rundir.TIMING_COLUMNS} for r in rs]

    assert len(key(rows(a))[0]) == 9 and key(rows(a)) == key(rows(b))


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


def test_a_run_killed_before_its_config_is_written_is_named_so_at_resume_and_its_command_reruns_there(tmp_path):
    """kill -9 in a run's first seconds (building its model and env, before config.yaml) leaves its directory holding
    only the lock file (the OS lock itself is released): --resume says what happened and what to do, in one line, and
    the command with --out that directory runs there."""
    killed = tmp_path / "killed"
    killed.mkdir()
    (killed / ".lock").write_text("12345\n")  # what such a kill leaves
    proc = cli("--resume", killed, check=False)
    (line,) = error_lines(proc.stderr)
    assert proc.returncode == 2 and "holds no run" in line and f"--out {killed}" in line, proc.stderr
    cli("--env", "invertedpendulum", "--trials", 1, *TINY, "--out", killed)
    assert [int(r["trial"]) for r in rows(killed)] == [0]
    proc = cli("--resume", tmp_path / "nothing", check=False)
    assert proc.returncode == 2 and "is not a run directory (no config.yaml)" in proc.stderr


def test_resume_can_extend_a_finished_run(tmp_path):
    out = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--out", out, *TINY)
    (out / "diverged.txt").write_text("trial 1: model training diverged\n")  # as a run that stopped diverged has
    cli("--resume", out, "--trials", 2)
    assert [int(r["trial"]) for r in rows(out)] == [0, 1]
    assert not (out / "diverged.txt").exists()  # a resumed run tries again: its record of a divergence is cleared


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


def test_a_new_run_or_training_in_a_folder_of_other_files_is_refused_and_touches_nothing(tmp_path):
    """run_pets.py and pets.train wrote a new run into any existing --out that held no config.yaml: a folder of one's
    own files (its metrics.csv written over), or a pets.compare output (a run mixed into the sweep's summaries).
    A new run now needs a new or empty --out, or one left with only its lock by a run killed in its first seconds."""
    from tests.processes import collect_random

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "metrics.csv").write_text("my own numbers\n")
    (mine / "notes.txt").write_text("mine\n")
    data = collect_random(tmp_path / "d.npz", 2)
    fragment = f"{mine} is not empty and holds no run (metrics.csv, notes.txt): a new run would write its files among"
    for command in (
        [sys.executable, str(ROOT / "run_pets.py"), "--env", "invertedpendulum", "--trials", 1, *TINY],
        [sys.executable, "-m", "pets.train", "--data", data, "--model", "delta", "--quiet", "model.max_epochs=2"],
    ):
        argv = [str(a) for a in [*command, "--out", mine]]
        proc = warm.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300)
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], proc.stderr
        assert sorted(p.name for p in mine.iterdir()) == ["metrics.csv", "notes.txt"]  # not even a lock file
        assert (mine / "metrics.csv").read_text() == "my own numbers\n"


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


def recorded_bars(monkeypatch) -> list[dict]:
    """The keyword arguments of every progress bar pets.loop creates from now on (the bars still draw)."""
    from pets import loop

    created = []

    class Recording(loop.tqdm):
        def __init__(self, *args, **kwargs):
            created.append(kwargs)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(loop, "tqdm", Recording)
    return created


def test_the_bar_over_trials_knows_its_total_and_shows_rate_and_eta(tmp_path, monkeypatch, capsys):
    """Issue 17 item 6: the trial-level bar is created with total=trials (initial=trials done on resume), so
    tqdm shows n/total, the rate and the remaining time."""
    import re

    import run_pets

    created = recorded_bars(monkeypatch)
    out = tmp_path / "run"
    visible = [a for a in TINY if a != "--quiet"]
    assert run_pets.main(["--env", "invertedpendulum", "--trials", "1", "--out", str(out), *visible]) == 0
    assert run_pets.main(["--resume", str(out), "--trials", "2"]) == 0
    bars = [(kw["total"], kw["initial"]) for kw in created if kw.get("unit") == "trial"]
    assert bars == [(1, 0), (2, 1)]
    err = capsys.readouterr().err.replace("\r", "\n")
    # e.g. "invertedpendulum-delta: 100%|##########| 2/2 [00:00<00:00,  1.63trial/s, reward=8.0, steps=41]"
    assert re.search(r"invertedpendulum-delta: +100%.* 2/2 \[\d\d:\d\d<\d\d:\d\d, +[\d.]+(trial/s|s/trial)", err), err


def test_a_run_ended_by_its_env_step_budget_shows_a_bar_over_env_steps(tmp_path, monkeypatch, capsys):
    """With ``max_env_steps`` (``--preset locomotion``: 100k, its trials an upper bound of 100,000) the bar counts
    env steps to the budget, seed data included, not the trials it will never reach; a resume starts it where the
    run stands, and its done line says the budget is spent; resuming it then prints no compile line."""
    import re

    import run_pets
    from pets import loop

    created = recorded_bars(monkeypatch)
    run = tmp_path / "run"
    visible = [a for a in TINY if a != "--quiet"]
    args = ["--env", "invertedpendulum", "--trials", "1000", "--out", str(run), *visible, "max_env_steps=200"]
    assert run_pets.main([*args[:3], "2", *args[4:]]) == 0  # stopped at 2 trials, short of the budget
    assert run_pets.main(["--resume", str(run), "--trials", "1000"]) == 0
    steps = [int(r["env_steps"]) for r in csv.DictReader(open(run / "metrics.csv"))]
    assert steps[-1] == 200
    bars = [(kw["total"], kw["initial"]) for kw in created if kw.get("unit") == "step"]
    assert bars == [(200, 0), (200, steps[1])] and not [kw for kw in created if kw.get("unit") == "trial"]
    out, err = capsys.readouterr()
    assert re.search(r"invertedpendulum-delta: +100%.* 200/200 \[", err.replace("\r", "\n")), err
    assert "200 env steps (its budget, max_env_steps: --trials runs it no further)" in out  # only the resume's
    assert out.count("its budget") == 1
    monkeypatch.setattr(loop, "compile_line", lambda cfg: "compile-line-probe")  # as if it compiled
    assert run_pets.main(["--resume", str(run), "--trials", "1000"]) == 0
    assert "compile-line-probe" not in capsys.readouterr().err  # nothing left to run: no "compiling once" line


def test_overrides_are_accepted_anywhere_on_the_command_line():
    """Issue 17 item 5: key=value after an option used to be 'unrecognized arguments'."""
    proc = cli("--env", "reacher", "threads=1", "--preset", "fast", "planner.population=50", "--trials", 0, check=False)
    assert proc.returncode == 2 and "trials must be >= 1, got 0" in proc.stderr  # parsed through to the config check
    assert "unrecognized arguments" not in proc.stderr


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
    from pets.data.datasets import load_dataset

    for content in (b"hello\n", bytes(range(256))):
        path = tmp_path / "data.npz"
        path.write_bytes(content)
        with pytest.raises(ValueError, match=r"is not an \.npz archive; data sets are written by pets\.collect"):
            load_dataset(path)


def test_atomic_writes_keep_the_usual_file_mode(tmp_path):
    """Atomic writes go through mkstemp (0600); the result must be as readable as a file written with open()."""
    from pets.runs.fileio import atomic_write_bytes

    atomic_write_bytes(tmp_path / "a.txt", b"x")
    (tmp_path / "b.txt").write_bytes(b"x")
    assert (tmp_path / "a.txt").stat().st_mode == (tmp_path / "b.txt").stat().st_mode


def _main(capsys, *argv):
    """run_pets.main in this process: (exit code, stdout, stderr)."""
    import run_pets

    try:
        code = run_pets.main([str(a) for a in argv])
    except SystemExit as err:
        code = err.code
    out = capsys.readouterr()
    return code, out.out, out.err


def test_print_config_round_trips_through_config_and_key_value_wins(tmp_path, capsys, monkeypatch):
    """Issue 35: --print-config prints the resolved config (nothing is run or written), valid as a --config file
    that gives the same config back; key=value and flags win over the file; a typo gets "did you mean"."""
    monkeypatch.chdir(tmp_path)
    code, printed, _ = _main(
        capsys, "--env", "ant", "--model", "gem-se", "--preset", "fast", "planner.horizon=9", "--print-config"
    )
    assert code == 0 and "head: gem-se" in printed and "horizon: 9" in printed and not (tmp_path / "runs").exists()
    file = tmp_path / "config.yaml"
    file.write_text(printed)
    assert _main(capsys, "--config", file, "--print-config")[1] == printed
    code, again, _ = _main(capsys, "--config", file, "planner.horizon=4", "--seed", 7, "--print-config")
    assert code == 0 and "horizon: 4" in again and "seed: 7" in again and "env: ant" in again
    (tmp_path / "partial.yaml").write_text("env: reacher\nplanner:\n  population: 33\nmodel.lr: 0.002\n")
    code, partial, _ = _main(capsys, "--config", tmp_path / "partial.yaml", "--print-config")
    assert code == 0 and "env: reacher" in partial and "population: 33" in partial and "lr: 0.002" in partial
    for content, fragment in (
        ("planner:\n  horizn: 3\n", "unknown config key 'planner.horizn'; did you mean planner.horizon?"),
        ("- a list\n", "expected a mapping of config keys, got a list"),
        ("env: [unclosed\n", "not a readable YAML file"),
        # a few hundred bytes of nested aliases held the process expanding them (killed after 12 CPU-s)
        ("a: &a [1, 1, 1]\nb: &b [*a, *a, *a]\nplanner:\n  feedback:\n    features: [*b, *b]\n", "aliases (*name)"),
        ("seed: 1\n" * 200_000, "over 1,000,000 bytes; a config file is a few KB"),  # /dev/zero was read forever
    ):
        (tmp_path / "bad.yaml").write_text(content)
        code, _, err = _main(capsys, "--env", "reacher", "--config", tmp_path / "bad.yaml", "--print-config")
        lines = error_lines(err)
        assert code == 2 and len(lines) == 1 and fragment in lines[0], err
