"""The run's env-step budget (``max_env_steps``: the last episode cut at it) and the training schedule by env steps
(``train_every=N train_after_trial=false``), run as a user would, on the real MuJoCo envs."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest

from tests.test_cli import ROOT, TINY, cli, error_lines, rows


def rows_of(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


MODEL_COLUMNS = ("model_train_loss", "model_val_loss", "model_val_loss_initial")


def test_a_run_stops_at_its_env_step_budget_with_the_last_episode_cut_there(tmp_path):
    out = tmp_path / "run"
    cli("--env", "hopper", "--trials", 50, "--out", out, *TINY, "max_env_steps=175")  # 100 seed steps + 75
    metrics = rows(out)
    assert [int(r["env_steps"]) for r in metrics][-1] == 175  # exactly the budget, well before 50 trials
    assert all(int(r["env_steps"]) <= 175 for r in metrics) and len(metrics) < 50
    assert sum(int(r["episode_length"]) for r in metrics) == 75  # the trials' steps: the budget less the seed data
    for r in metrics[:-1]:  # every episode but the last ended by a fall or by the 30-step limit
        assert r["terminated"] == "1" or r["episode_length"] == "30", r
    again = cli("--resume", out, "--quiet")  # a finished run resumed: nothing more to do
    assert again.returncode == 0 and rows(out) == metrics
    # the gate's per-run row of it (pets.experiments.gate), as a user runs it
    proc = subprocess.run(
        [sys.executable, "-m", "pets.experiments.gate", str(out), "--out", str(tmp_path / "gate")],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    (row,) = rows_of(tmp_path / "gate_runs.csv")
    falls = sum(r["terminated"] == "1" for r in metrics)
    assert row["env"] == "hopper" and row["env_steps"] == "175" and row["episodes"] == str(len(metrics))
    assert float(row["fall_fraction"]) == pytest.approx(falls / len(metrics), abs=1e-4)
    assert row["status"] == "complete" and row["reward_100k"] == ""  # a budget of 175 steps: no 100k endpoint


def test_training_every_n_env_steps_crosses_episodes_and_skips_trials_in_between(tmp_path):
    # seed data 100 steps, then 30-step trials ending at 130, 160, 190, 220: multiples of 60 at 120 (trial 0), 180
    # (trial 2); trials 1 and 3 do not train, so their model columns repeat the trial before.
    out = tmp_path / "steps"
    cli("--env", "halfcheetah", "--trials", 4, *TINY, "train_every=60", "train_after_trial=false", "--out", out)
    metrics = rows(out)
    same = [all(a[c] == b[c] for c in MODEL_COLUMNS) for a, b in zip(metrics, metrics[1:])]
    assert same == [True, False, True], metrics  # trials 1 and 3 repeat the model columns, trial 2 trained


@pytest.mark.parametrize(
    "overrides, says",
    [
        (["train_after_trial=false"], "train_after_trial=false needs train_every"),
        (["max_env_steps=100"], "max_env_steps must be null or above seed_steps (100)"),
    ],
)
def test_a_schedule_that_cannot_run_is_one_line_exit_2(tmp_path, overrides, says):
    proc = cli("--env", "halfcheetah", "--trials", 1, "--out", tmp_path / "r", *TINY, *overrides, check=False)
    assert proc.returncode == 2 and len(error_lines(proc.stderr)) == 1 and says in proc.stderr, proc.stderr
