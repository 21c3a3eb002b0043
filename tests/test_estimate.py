"""pets.compare online --estimate (pets.experiments.estimate): the runs still to do, their planned env steps and
gradient steps counted from the config (against hand arithmetic and the real loop's metrics.csv), the CPU-hours
from per-step figures; nothing is run or written."""

from __future__ import annotations

import csv

import pytest

from pets.config import make_config
from pets.experiments import estimate as est
from pets.experiments.cli import main
from tests.tiny import TINY_MODEL, TINY_PLANNER

TINY = [*TINY_PLANNER, *TINY_MODEL, "episode_length=30", "seed_steps=100", "model.iterations=5"]
SWEEP = ["online", "--envs", "invertedpendulum", "--models", "delta", "--seeds", "0", "--preset", "fast", "--quiet"]


def test_a_runs_planned_and_gradient_steps_follow_its_budget_and_schedule():
    loco = make_config("halfcheetah", "delta", "locomotion", {})
    # 100k env steps less the 1,000 random seed steps are planned; one training of 1,000 steps every 1,000 env steps
    assert est.run_shape(loco, 1000) == (99_000, 99_000)
    assert est.run_shape(loco, 1000, steps_done=50_000) == (50_000, 50_000)  # a resumed run: what is left
    assert est.run_shape(loco, 1000, steps_done=100_000) == (0, 0)
    epochs = make_config("halfcheetah", "delta", "locomotion", {"model.iterations": 0})
    assert est.run_shape(epochs, 1000) == (99_000, None)  # training by epochs: not projected
    trials = make_config("invertedpendulum", "delta", "fast", {"trials": 7, "model.iterations": 50})
    assert est.run_shape(trials, 200) == (1400, 7 * 50)  # no budget: trials x length, one training after each
    # resumed after 3 trials that ended early (50 steps each): its 4 trials left, not the 7 x 200 less the steps done
    assert est.run_shape(trials, 200, steps_done=trials.seed_steps + 150, trials_done=3) == (800, 4 * 50)
    assert est.run_shape(loco, 1000, steps_done=50_000, trials_done=20) == (50_000, 50_000)  # the budget binds


def test_the_projection_multiplies_the_measured_steps_and_skips_reused_runs(tmp_path):
    def loco(head: str, **over: object):  # on the CPU: a CUDA run's projection is in hours of wall time
        return make_config("halfcheetah", head, "locomotion", {"device": "cpu", **over})

    cfgs = {f"halfcheetah-{m}-s{s}": loco(m, seed=s) for m in ("delta", "gem") for s in (0, 1)}
    seen = []

    def measure(cfg):
        seen.append(cfg.head)
        return (0.1, 0.02) if cfg.head == "delta" else (0.2, 0.06)

    actions = {"halfcheetah-delta-s1": "reuse"}
    text = est.estimate(cfgs, actions, tmp_path, workers=2, measure=measure)
    assert seen == ["delta", "gem"]  # once per env and arm
    lines = text.splitlines()
    # delta: 1 run, 99,000 steps x 0.1 s = 2.75 h planning; 99,000 gradient steps x 0.02 s = 0.55 h
    assert lines[2] == "| halfcheetah-delta | 1 | 99,000 | 2.75 (0.1 s a step) | 0.55 (0.02 s a step) | 3.3 |"
    assert lines[3] == "| halfcheetah-gem | 2 | 198,000 | 11 (0.2 s a step) | 3.3 (0.06 s a step) | 14.3 |"
    assert lines[5].startswith("3 runs, about 17.6 CPU-hours (8.8 h of wall time on 2 worker(s))")
    everything = dict.fromkeys(cfgs, "reuse")
    assert est.estimate(cfgs, everything, tmp_path, 2, measure).startswith("nothing to run")
    epochs = {"halfcheetah-delta-s0": loco("delta", **{"model.iterations": 0})}
    text = est.estimate(epochs, {}, tmp_path, None, lambda cfg: (0.1, None))
    assert "| 2.75 (0.1 s a step) | not projected (epochs) | 2.75 |" in text and "wall time" not in text  # Ray
    assert "training by epochs not included; the value fit" in text and "measured eager" not in text
    assert "\n\n1 run, about 2.75 CPU-hours, measured" in text
    sparse = {"halfcheetah-delta-s0": loco("delta", **{"planner.replan_every": 5})}
    text = est.estimate(sparse, {}, tmp_path, 1, lambda cfg: (0.1, 0.02))  # one plan per 5 env steps: 19,800 plans
    assert "| halfcheetah-delta | 1 | 99,000 | 0.55 (0.1 s a step) | 0.55 (0.02 s a step) | 1.1 |" in text


def test_estimate_measures_on_this_machine_counts_a_resumed_run_by_what_is_left_and_writes_nothing(
    tmp_path, capsys, monkeypatch
):
    out = tmp_path / "sweep"
    assert main([*SWEEP, "--trials", "4", "--out", str(out), "--estimate", *TINY]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].startswith("| env and arm | runs to do | planned env steps |") and not out.exists()
    row = table[2].split(" | ")
    assert row[:3] == ["| invertedpendulum-delta", "1", "120"]  # 4 trials x 30 steps
    plan_h, train_h = (float(cell.split(" (")[0]) for cell in row[3:5])
    assert plan_h > 0 and train_h > 0 and float(row[5].rstrip(" |")) == pytest.approx(plan_h + train_h, rel=0.01)
    assert main([*SWEEP, "--trials", "2", "--out", str(out), *TINY]) == 0  # 2 of the 4 trials, for real
    with open(out / "runs" / "invertedpendulum-delta-s0" / "metrics.csv", newline="") as f:
        done = int(list(csv.DictReader(f))[-1]["env_steps"])
    capsys.readouterr()
    monkeypatch.setattr(est, "_measure", lambda cfg: (0.01, 0.001))  # measured above: only the count matters now
    assert main([*SWEEP, "--trials", "4", "--out", str(out), "--estimate", *TINY]) == 0
    row = capsys.readouterr().out.splitlines()[2].split(" | ")
    assert row[1:3] == ["1", "60"]  # what is left: 2 trials of 30 steps, however long the first 2 were
    assert done - 100 <= 60  # (they ended at or before 30 steps each)


def test_without_out_every_run_is_to_do_and_no_directory_is_looked_at(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(est, "_measure", lambda cfg: (0.01, 0.001))
    monkeypatch.chdir(tmp_path)
    stray = tmp_path / "runs" / "invertedpendulum-delta-s0"
    stray.mkdir(parents=True)
    (stray / "config.yaml").write_text("env: reacher\n")  # another config: a sweep into . would refuse it
    assert main([*SWEEP, "--seeds", "0,1", "--trials", "4", "--estimate", *TINY]) == 0
    row = capsys.readouterr().out.splitlines()[2]
    assert row.startswith("| invertedpendulum-delta | 2 | 240 |") and sorted(p.name for p in tmp_path.iterdir()) == [
        "runs"
    ]
    with pytest.raises(SystemExit) as exit_info:
        main([*SWEEP, "--trials", "4", *TINY])  # a sweep itself still needs --out
    assert exit_info.value.code == 2 and "--out is required" in capsys.readouterr().err
