"""What ``run_pets.py --resume DIR`` may change and what it refuses in one line (issue 55): a missing checkpoint of a
run that completed trials, ``--preset``, ``--trials`` below the trials done; ``threads=N`` is allowed (speed only)."""

from __future__ import annotations

import pytest

from tests.test_cli import TINY, cli, error_lines, rows

METRIC_KEYS = ("trial", "env_steps", "episode_reward", "episode_length", "model_train_loss", "model_val_loss")


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    run = tmp_path_factory.mktemp("resume") / "run"
    cli("--env", "invertedpendulum", "--model", "delta", "--trials", 2, "--out", run, *TINY)
    return run


def _refused(*args: object) -> str:
    proc = cli(*args, check=False)
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    return lines[0]


def test_a_missing_checkpoint_of_a_run_with_trials_is_refused_and_its_metrics_kept(finished, tmp_path):
    run = tmp_path / "copy"
    run.mkdir()
    for name in ("config.yaml", "metrics.csv", "history.csv"):
        (run / name).write_bytes((finished / name).read_bytes())
    before = (run / "metrics.csv").read_bytes()
    line = _refused("--resume", run)
    assert "checkpoint.pt is missing although the run records 2 completed trial(s)" in line
    assert (run / "metrics.csv").read_bytes() == before


def test_preset_with_resume_is_refused(finished):
    assert "--preset research is refused" in _refused("--resume", finished, "--preset", "research")


def test_fewer_trials_than_done_is_refused(finished):
    assert "--trials 1 is fewer than the 2 trials" in _refused("--resume", finished, "--trials", 1)


def test_other_settings_on_resume_are_refused_naming_them(finished):
    assert "got planner.horizon" in _refused("--resume", finished, "planner.horizon=7")


def test_threads_on_resume_is_allowed_and_changes_no_result(finished, tmp_path):
    longer = tmp_path / "longer"
    cli("--env", "invertedpendulum", "--model", "delta", "--trials", 3, "--out", longer, *TINY)
    run = tmp_path / "moved"
    run.mkdir()
    for path in finished.iterdir():
        if path.is_file():
            (run / path.name).write_bytes(path.read_bytes())
    cli("--resume", run, "--trials", 3, "threads=2", "--quiet")
    got, want = rows(run), rows(longer)
    assert [[r[k] for k in METRIC_KEYS] for r in got] == [[r[k] for k in METRIC_KEYS] for r in want]


def _older_run(finished, run, keep_in_file: dict | None = None):
    """A copy of ``finished`` as a run started before ``planner.termination_penalty`` existed: the key in neither its
    checkpoint nor its config.yaml (``keep_in_file``: what the file says for it instead)."""
    import torch
    import yaml

    run.mkdir()
    for path in finished.iterdir():
        if path.is_file():
            (run / path.name).write_bytes(path.read_bytes())
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    del state["config"]["planner"]["termination_penalty"]
    torch.save(state, run / "checkpoint.pt")
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    del cfg["planner"]["termination_penalty"]
    cfg["planner"].update(keep_in_file or {})
    (run / "config.yaml").write_text(yaml.safe_dump(cfg))


def test_a_run_started_before_a_key_existed_resumes_with_its_default(finished, tmp_path):
    run = tmp_path / "older"
    _older_run(finished, run)
    cli("--resume", run, "--trials", 3, "--quiet")
    assert [r["trial"] for r in rows(run)] == ["0", "1", "2"]
    edited = tmp_path / "older-edited"
    _older_run(finished, edited, {"termination_penalty": 5.0})  # written into the file after the start: an edit
    assert "planner.termination_penalty: None in the checkpoint, 5.0 in config.yaml" in _refused("--resume", edited)


def test_the_history_names_the_cpu_of_every_session_and_takes_the_column_into_an_old_history(tmp_path):
    """The CPU behind a run's CPU-hours is recorded per session (a resumed run may have moved machines); a history
    written before the column keeps its rows, their CPU unknown (empty)."""
    from pets.runs import rundir
    from pets.runs.hardware import cpu_isa

    (tmp_path / rundir.HISTORY_FILE).write_text("time,action,trials_done,host,pid\n2026-11-27T10:00:00,start,0,vm,7\n")
    rundir.append_history(tmp_path, "resume", 4)
    old, new = rundir.read_history(tmp_path)
    assert (old["action"], old["pid"], old["cpu"]) == ("start", "7", None)
    assert (new["action"], new["trials_done"]) == ("resume", "4") and new["cpu"].endswith(f"({cpu_isa()})")
