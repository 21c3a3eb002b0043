"""docs/scripts/frozen_model_checks.py: a run's frozen model planning in the real env under planner variants, and its
open-loop reward prediction along the run's own actions (the locomotion gate's Ant diagnosis)."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest
import torch

import envs
from tests import warm
from tests.test_cli import ROOT, TINY, cli

SCRIPT = ROOT / "docs" / "scripts" / "frozen_model_checks.py"


def check(*args: object) -> subprocess.CompletedProcess:
    return warm.run([sys.executable, str(SCRIPT), *map(str, args)], cwd=ROOT, capture_output=True, text=True,
                    timeout=300)  # fmt: skip


@pytest.fixture(scope="module")
def hopper_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("frozen") / "hopper"
    cli("--env", "hopper", "--seed", 1, *TINY, "value.enabled=true", "value.steps=20", "--trials", 2, "--out", run)
    return run


def test_plan_rows_replay_the_same_starts_and_a_zero_risk_is_the_base_planner(hopper_run, tmp_path):
    out = tmp_path / "plan.csv"
    proc = check("plan", hopper_run, "--variants", "base", "risk=0", "planner.horizon=3", "pen=1000", "novalue",
                 "--episodes", 2, "--steps", 15, "--out", out)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.DictReader(out.open()))
    assert [r["variant"] for r in rows] == [v for v in ("base", "risk=0", "planner.horizon=3", "pen=1000", "novalue")
                                            for _ in range(2)]  # fmt: skip
    base, risk = rows[:2], rows[2:4]
    assert [(r["steps"], r["reward"], r["height"]) for r in base] == [(r["steps"], r["reward"], r["height"])
                                                                      for r in risk]  # fmt: skip
    for r in rows:
        assert 1 <= int(r["steps"]) <= 15 and r["fell"] in ("0", "1")
        assert r["fell"] == "1" or int(r["steps"]) == 15
    bad = check("plan", hopper_run, "--variants", "wobble=1", "--out", tmp_path / "x.csv")
    assert bad.returncode != 0 and "unknown variant 'wobble=1'" in bad.stderr


def test_reward_rows_match_the_model_and_the_envs_own_reward_at_one_step(hopper_run, tmp_path):
    out = tmp_path / "reward.csv"
    proc = check("reward", hopper_run, "--horizons", 1, 3, "--out", out)
    assert proc.returncode == 0, proc.stderr
    one, three = list(csv.DictReader(out.open()))
    assert (one["horizon"], three["horizon"], one["windows"]) == ("1", "3", "400")
    buffer = torch.load(hopper_run / "checkpoint.pt", weights_only=False)["buffer"]
    # the true one-step sums are rewards of real transitions: their mean lies within the buffer's range
    rew = envs.get("hopper").reward(*(torch.as_tensor(buffer[k]).float() for k in ("obs", "act", "next_obs")))
    assert float(rew.min()) <= float(one["true_mean"]) <= float(rew.max())
    assert -1.0 <= float(one["corr"]) <= 1.0 and float(one["mean_abs_error"]) >= 0


def test_the_frozen_planning_block_counts_falls_and_averages_per_run_and_variant(tmp_path):
    from pets.experiments.gate_published import frozen_planning_table
    from pets.experiments.report import write_csv

    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    rows = [
        {"run": "ant", "variant": v, "episode": e, "steps": n, "reward": r, "fell": f, "height": 0.5, "cpu_s": 1}
        for v, e, n, r, f in (("base", 0, 100, 10.0, 1), ("base", 1, 300, 50.0, 0), ("zero", 0, 300, 296.0, 0))
    ]
    write_csv(results / "locomotion_frozen_planning.csv", rows, list(rows[0]))
    lines = frozen_planning_table(tmp_path).splitlines()
    assert lines[2:] == ["| ant | base | 2 | 1 | 200 | 30 |", "| ant | zero | 1 | 0 | 300 | 296 |"]


def test_falls_rows_count_the_buffers_falls_by_the_envs_own_termination(hopper_run, tmp_path):
    """Every Hopper episode of a tiny run ends in a fall or at the 30-step limit; one step before a fall the model's
    prediction is checked against the env's own termination function, so the count of falls is Hopper's."""
    from pets.planning.value import episode_ends

    out = tmp_path / "falls.csv"
    proc = check("falls", hopper_run, "--horizons", 1, 2, "--out", out)
    assert proc.returncode == 0, proc.stderr
    one, two = list(csv.DictReader(out.open()))
    buffer = torch.load(hopper_run / "checkpoint.pt", weights_only=False)["buffer"]
    obs, act, nxt = (torch.as_tensor(buffer[k]).float() for k in ("obs", "act", "next_obs"))
    last = torch.nonzero(episode_ends(obs, nxt)).flatten()
    env_falls = int(envs.get("hopper").terminated(obs[last], act[last], nxt[last]).sum())
    assert int(one["falls"]) == env_falls > 0 and int(two["falls"]) <= env_falls
    assert 0 <= int(one["foreseen"]) <= env_falls and float(one["recall"]) == pytest.approx(
        int(one["foreseen"]) / env_falls, abs=1e-4
    )


def test_episode_ends_rows_cover_the_buffer_with_each_episodes_mean_squared_action(hopper_run, tmp_path):
    """docs/scripts/episode_ends.py: the episodes' steps add up to the buffer, and action_sq is each episode's mean
    squared action norm, recomputed here from the buffer's actions."""
    out = tmp_path / "ends.csv"
    proc = warm.run([sys.executable, str(ROOT / "docs" / "scripts" / "episode_ends.py"), str(hopper_run),
                    "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.DictReader(out.open()))
    act = torch.as_tensor(torch.load(hopper_run / "checkpoint.pt", weights_only=False)["buffer"]["act"]).double()
    assert sum(int(r["steps"]) for r in rows) == len(act)
    start = 0
    for r in rows:
        n = int(r["steps"])
        assert float(r["action_sq"]) == pytest.approx(float(act[start : start + n].square().sum(-1).mean()), abs=1e-3)
        start += n


def test_the_episode_ends_block_counts_jumps_backs_and_planned_full_episodes(tmp_path):
    from pets.experiments.gate_published import episode_ends_table
    from pets.experiments.report import write_csv

    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    rows = [  # the first episode is the seed data's (random): not a planned one
        {"run": "ant", "episode": e, "steps": n, "fell": f, "action_sq": a, "height": h, "up_cos": u}
        for e, n, f, a, h, u in (
            (0, 1000, 0, 2.7, 0.5, 1.0),
            (1, 40, 1, 1.0, 1.05, 0.9),
            (2, 1000, 0, 0.5, 0.27, -0.9),
            (3, 1000, 0, 1.5, 0.6, 0.99),
        )  # fmt: skip
    ]
    write_csv(results / "locomotion_episode_ends.csv", rows, list(rows[0]))
    assert episode_ends_table(tmp_path).splitlines()[2] == "| ant | 4 | 1 | 1 | 1 | 2 | 1 |"
