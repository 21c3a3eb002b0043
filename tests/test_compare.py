"""pets.compare (online and offline A/B runs) and pets.openloop end to end, on tiny configs.

The comparison commands run in-process through their CLI entry point ``main`` (argument parsing,
exit codes, files); the online runs themselves are real ``run_pets.py`` subprocesses. Ground truth:
the runs' own metrics.csv / eval.json, pets.experiments.statistics recomputed here, and the MuJoCo simulator for the
open-loop rewards.
"""

import csv
import importlib.util
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
from rliable import library, metrics

import envs
from pets import openloop
from pets.config import load_config, make_config
from pets.experiments import arguments, runner
from pets.experiments import cli as cli_module
from pets.experiments import offline as offline_mod
from pets.experiments.arguments import UsageError
from pets.experiments.cli import EXIT_FAILED, main
from pets.experiments.headline import HeadlineError, write_headline
from pets.experiments.offline import compare_offline
from pets.experiments.offline_summary import summarise_offline
from pets.experiments.online import compare_online
from pets.experiments.report import fmt, fmt_interval, write_csv
from pets.experiments.rundirs import arm_run_dir
from pets.experiments.statistics import REPS, ci_exact_note, holm, sign_flip_p
from pets.experiments.studies.offline import SUMMARY_COLUMNS, summary_from_runs
from pets.experiments.studies.online import STUDY as ONLINE_STUDY
from pets.experiments.studies.online import SUMMARY_COLUMNS as ONLINE_COLUMNS
from pets.experiments.studies.online import summarise_online
from pets.runs import rundir
from tests.processes import alive, default_sigint
from tests.threads import one_thread
from tests.tiny import TINY_MODEL, TINY_PLANNER

ROOT = Path(__file__).resolve().parents[1]

TINY = [
    *TINY_PLANNER,
    *TINY_MODEL,
    "episode_length=30",
    "seed_steps=100",
]
TINY_OFFLINE = [
    "model.max_epochs=3",
    "model.hidden_size=32",
    "model.ensemble_size=2",
    "model.num_elites=2",
    "model.batch_size=32",
    "planner.population=16",
    "planner.particles=2",
    "planner.iterations=2",
]


ONLINE_BASELINE_COLUMNS = ONLINE_COLUMNS[ONLINE_COLUMNS.index("p_improvement") :]


def rliable_iqm_columns(scores):
    return np.array([metrics.aggregate_iqm(scores[:, j]) for j in range(scores.shape[1])])


def cli(capsys, *args):
    """``python -m pets.compare ARGS`` in this process: (exit code, stdout, stderr)."""
    try:
        code = main([str(a) for a in args])
    except SystemExit as err:
        code = err.code
    out = capsys.readouterr()
    return code, out.out, out.err


def csv_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def snapshot(run_dir):
    return {name: (run_dir / name).stat().st_mtime_ns for name in ("config.yaml", "metrics.csv", "checkpoint.pt")}


# --------------------------------------------------------------------------- online
@pytest.fixture(scope="module")
def online(tmp_path_factory):
    """Three invocations: (1) delta seeds 0 and 9 for 1 trial, seed 9 a broken run; (2) delta and gem, seeds 0
    and 1, 2 trials (delta-s0 must be resumed); (3) the same again (everything reused)."""
    out = tmp_path_factory.mktemp("online")
    common = ["--envs", "invertedpendulum", "--out", out, "--workers", 2, "--preset", "fast", "--quiet", *TINY]
    # a broken run directory: valid config, corrupted checkpoint, no completed trial -> its resume fails
    broken = out / "runs" / "invertedpendulum-delta-s9"
    broken.mkdir(parents=True)
    overrides = dict(item.split("=") for item in TINY)
    rundir.write_config(
        broken, make_config("invertedpendulum", "delta", "fast", {**overrides, "seed": 9, "trials": 1, "threads": 1})
    )
    (broken / "checkpoint.pt").write_bytes(b"not a checkpoint")

    steps = {}
    for key, args in (
        ("first", ["--models", "delta", "--seeds", "0,9", "--trials", 1]),
        ("second", ["--models", "delta,gem", "--seeds", "0,1", "--trials", 2]),
        ("third", ["--models", "delta,gem", "--seeds", "0,1", "--trials", 2]),
    ):
        before = {
            d.name: (snapshot(d), csv_rows(d / "metrics.csv"))
            for d in (out / "runs").iterdir()
            if (d / "metrics.csv").exists()
        }
        try:
            code = main([str(a) for a in ["online", *args, *common]])
        except SystemExit as err:
            code = err.code
        steps[key] = {
            "code": code,
            "before": before,
            "summary": (out / "summary.csv").read_text(),
            "md": (out / "summary.md").read_text(),
        }
    return out, steps


def test_online_failed_run_is_reported_and_the_others_go_on(online):
    out, steps = online
    first = steps["first"]
    assert first["code"] == EXIT_FAILED
    rows = list(csv.DictReader(first["summary"].splitlines()))
    assert len(rows) == 1 and rows[0]["model"] == "delta" and rows[0]["n_seeds"] == "1"
    assert "invertedpendulum-delta-s9 (0/1 trials; failed: RuntimeError: exit 2" in first["md"]
    log = (out / "logs" / "invertedpendulum-delta-s9.log").read_text()
    assert "checkpoint.pt is not a readable checkpoint" in log and "Traceback" not in log  # one line (issue 17)


def test_online_incomplete_run_is_resumed_not_restarted(online):
    out, steps = online
    assert steps["second"]["code"] == 0
    run = out / "runs" / "invertedpendulum-delta-s0"
    snap, rows_after_first = steps["second"]["before"]["invertedpendulum-delta-s0"]
    assert len(rows_after_first) == 1
    # a restart would rewrite config.yaml and re-measure trial 0 (wall time); a resume appends trial 1
    assert (run / "config.yaml").stat().st_mtime_ns == snap["config.yaml"]
    rows = csv_rows(run / "metrics.csv")
    assert [r["trial"] for r in rows] == ["0", "1"] and rows[0] == rows_after_first[0]
    log = (out / "logs" / "invertedpendulum-delta-s0.log").read_text()
    assert log.count("run_pets.py --env") == 1 and log.count(f"run_pets.py --resume {run} --trials 2") == 1


def test_online_rerun_reuses_everything(online):
    out, steps = online
    assert steps["third"]["code"] == 0
    for name, (snap, rows) in steps["third"]["before"].items():
        if name.endswith("-s9"):
            continue
        assert snapshot(out / "runs" / name) == snap, name  # nothing was touched
        assert len(rows) == 2
    assert steps["third"]["summary"] == steps["second"]["summary"]
    assert steps["third"]["md"] == steps["second"]["md"]  # byte for byte, the command line it names included
    line = f"online --models delta,gem --seeds 0,1 --trials 2 --envs invertedpendulum --out {out} --workers 2"
    assert f"- command: `python -m pets.compare {line} --preset fast --quiet {' '.join(TINY)}`" in steps["third"]["md"]
    assert sum(1 for _ in (out / "logs").iterdir()) == 5  # 4 runs + the broken one, no new logs


def test_online_summary_equals_statistics_recomputed_from_metrics(online):
    out, _ = online
    summary = {(r["env"], r["model"]): r for r in csv_rows(out / "summary.csv")}
    assert set(summary) == {("invertedpendulum", "delta"), ("invertedpendulum", "gem")}
    finals = {}
    for model in ("delta", "gem"):
        scores = []
        for seed in (0, 1):
            rows = csv_rows(out / "runs" / f"invertedpendulum-{model}-s{seed}" / "metrics.csv")
            rewards = [float(r["episode_reward"]) for r in rows]
            assert len(rewards) == 2
            scores.append([np.mean(rewards[-2:]), np.mean(rewards)])  # --final-window 3, capped at the 2 trials
        scores = np.array(scores)
        finals[model] = scores[:, 0]
        row = summary[("invertedpendulum", model)]
        assert int(row["n_seeds"]) == 2 and int(row["n_diverged"]) == 0
        assert int(row["trials"]) == 2 and int(row["final_window"]) == 2
        # rliable on the same (seeds, [final, auc]) matrix, numpy's global generator seeded with 0
        np.random.seed(0)
        point, interval = library.get_interval_estimates({"x": scores}, rliable_iqm_columns, reps=REPS)
        for j, key in enumerate(("final", "auc")):
            assert float(row[f"{key}_iqm"]) == point["x"][j] == pytest.approx(scores[:, j].mean(), rel=1e-12)
            assert (float(row[f"{key}_ci_low"]), float(row[f"{key}_ci_high"])) == tuple(interval["x"][:, j])
            assert (float(row[f"{key}_ci_low"]), float(row[f"{key}_ci_high"])) == (min(scores[:, j]), max(scores[:, j]))
        walls = [
            float(csv_rows(out / "runs" / f"invertedpendulum-{model}-s{seed}" / "metrics.csv")[1]["wall_time_s"])
            for seed in (0, 1)
        ]
        assert float(row["wall_time_s_mean"]) == pytest.approx(np.mean(walls), rel=1e-12) and min(walls) > 0
        assert float(row["plan_seconds_per_step_mean"]) > 0 and row["planner"] == ""
    assert all(summary[("invertedpendulum", "delta")][c] == "" for c in ONLINE_BASELINE_COLUMNS)
    gem = summary[("invertedpendulum", "gem")]
    p = metrics.probability_of_improvement(finals["gem"][:, None], finals["delta"][:, None])
    assert float(gem["p_improvement"]) == pytest.approx(p, abs=1e-15)
    diffs = finals["gem"] - finals["delta"]
    assert float(gem["diff_to_delta"]) == pytest.approx(diffs.mean(), rel=1e-12, abs=1e-12)
    assert (float(gem["diff_ci_low"]), float(gem["diff_ci_high"])) == pytest.approx((min(diffs), max(diffs)))
    assert gem["n_pairs"] == "2"
    md = (out / "summary.md").read_text()
    assert "| delta | 2 | 0 |" in md and "| gem | 2 | 0 |" in md and "rewards_invertedpendulum.png" in md
    assert "Fewer than 5 seeds cannot carry a claim" in md
    assert (out / "rewards_invertedpendulum.png").stat().st_size > 10_000
    assert (out / "walltime_invertedpendulum.png").stat().st_size > 10_000
    assert len(csv_rows(out / "summary_runs.csv")) == 4


def test_online_planners_axis_runs_every_model_planner_pair(tmp_path, capsys):
    code, printed, stderr = cli(
        capsys,
        "online",
        "--envs",
        "invertedpendulum",
        "--models",
        "delta",
        "--planners",
        "cem,icem",
        "--seeds",
        3,
        "--trials",
        1,
        "--out",
        tmp_path,
        "--workers",
        2,
        "--preset",
        "fast",
        "--quiet",
        *TINY,
    )
    assert code == 0 and stderr.count("pets.compare: warning: 1 seed: fewer than 5 seeds") == 1
    for planner in ("cem", "icem"):
        run = tmp_path / "runs" / f"invertedpendulum-delta-{planner}-s3"
        assert load_config(str(run / "config.yaml")).planner.name == planner
        assert len(csv_rows(run / "metrics.csv")) == 1
    summary = csv_rows(tmp_path / "summary.csv")
    assert [(r["model"], r["planner"], r["n_seeds"]) for r in summary] == [
        ("delta", "cem", "1"),
        ("delta", "icem", "1"),
    ]
    assert "| model | planner | seeds |" in printed and "| delta | icem | 1 |" in printed
    assert (tmp_path / "walltime_invertedpendulum.png").stat().st_size > 10_000


def test_one_planner_reuses_the_runs_made_without_planners_where_their_config_is_the_same(tmp_path, capsys):
    """``--planners mppi`` (the fast preset's planner of invertedpendulum) on a sweep run without the flag: the
    same runs, reused, not run again as ENV-MODEL-mppi-sSEED; a run made without the flag with another planner is not
    this arm's, and one with this planner but another config is refused (one line, exit 2), never reused."""
    base = ["online", "--envs", "invertedpendulum", "--models", "delta", "--seeds", "0,1", "--trials", 2, "--preset",
            "fast", "--out", tmp_path, "--quiet", *TINY]  # fmt: skip
    configs = compare_online(["invertedpendulum"], ["delta"], [0, 1], 2, tmp_path, preset="fast", overrides=TINY,
                             configs_only=True)["configs"]  # fmt: skip
    for seed, rewards in ((0, [1.0, 2.0]), (1, [3.0, 5.0])):
        run = tmp_path / "runs" / f"invertedpendulum-delta-s{seed}"
        fake_run(tmp_path, "invertedpendulum", "delta", seed, rewards)
        rundir.write_config(run, configs[run.name])
    code, _, err = cli(capsys, *base, "--planners", "mppi")
    assert code == 0 and "2 runs: 2 reused, 0 to resume, 0 to start" in err, err
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == [
        "invertedpendulum-delta-s0",
        "invertedpendulum-delta-s1",
    ]
    (row,) = csv_rows(tmp_path / "summary.csv")
    assert (row["model"], row["planner"], row["n_seeds"], float(row["final_iqm"])) == ("delta", "mppi", "2", 2.75)
    runs = tmp_path / "runs"
    assert arm_run_dir(runs, "invertedpendulum", "delta", 0, "cem") == runs / "invertedpendulum-delta-cem-s0"
    changed = load_config(str(runs / "invertedpendulum-delta-s1" / "config.yaml"))
    changed.planner.horizon += 1
    rundir.write_config(runs / "invertedpendulum-delta-s1", changed)
    code, _, err = cli(capsys, *base, "--planners", "mppi")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "invertedpendulum-delta-s1 was made with another config" in lines[0], err
    assert "planner.horizon" in lines[0] and len(list(runs.iterdir())) == 2


# --------------------------------------------------------------------------- online summary on fake runs
FAKE_TRIALS, FAKE_WINDOW = 4, 2
REWARD_BONUS = {"delta": 0.0, "gem": 3.0, "gem2": -2.0}


def fake_rewards(model, seed, planner=None):
    """Episode rewards per trial: rising, gem above delta, gem2 below; the seeds differ by different amounts."""
    bonus = REWARD_BONUS[model] + (5.0 if planner == "icem" else 0.0)
    return [10.0 * t + (1.0 + 0.5 * (model == "gem")) * seed + bonus for t in range(FAKE_TRIALS)]


def fake_run(out, env, model, seed, rewards, planner=None, cpu=False):
    """A run directory with only a metrics.csv of ``len(rewards)`` trials (``cpu``: with the ``cpu_time_s`` column,
    5 (t + 1) + seed; without it, a run made before the column)."""
    run = out / "runs" / (f"{env}-{model}-s{seed}" if planner is None else f"{env}-{model}-{planner}-s{seed}")
    run.mkdir(parents=True)
    lines = ["trial,env_steps,episode_reward,wall_time_s,plan_seconds_per_step" + (",cpu_time_s" if cpu else "")]
    lines += [
        f"{t},{100 * (t + 1)},{r!r},{10.0 * (t + 1) + seed},{0.1 if t else 0.0}"
        + (f",{5 * (t + 1) + seed}" if cpu else "")
        for t, r in enumerate(rewards)
    ]
    (run / "metrics.csv").write_text("\n".join(lines) + "\n")


def fake_finals(model, seed, planner=None):
    return float(np.mean(fake_rewards(model, seed, planner)[-FAKE_WINDOW:]))


@pytest.fixture(scope="module")
def fake_online(tmp_path_factory):
    """reacher: delta, gem, gem2 with 5 seeds; gem seed 2 has a NaN reward in trial 1, gem2 seed 0 an inf in the
    last trial; gem seed 4 of delta is incomplete. hopper: delta 2 seeds, gem both seeds NaN."""
    out = tmp_path_factory.mktemp("fake-online")
    for model in ("delta", "gem", "gem2"):
        for seed in range(5):
            rewards = fake_rewards(model, seed)
            if (model, seed) == ("gem", 2):
                rewards[1] = math.nan
            if (model, seed) == ("gem2", 0):
                rewards[-1] = -math.inf
            if (model, seed) == ("delta", 4):
                rewards = rewards[:2]
            fake_run(out, "reacher", model, seed, rewards)
    for seed in range(2):
        fake_run(out, "hopper", "delta", seed, fake_rewards("delta", seed))
        fake_run(out, "hopper", "gem", seed, [math.nan] * FAKE_TRIALS)
    rows = summarise_online(
        out, ["reacher", "hopper"], ["delta", "gem", "gem2"], range(5), FAKE_TRIALS, FAKE_WINDOW, reps=300
    )
    return out, rows


def online_row(out, env, model, planner=""):
    (row,) = [r for r in csv_rows(out / "summary.csv") if (r["env"], r["model"], r["planner"]) == (env, model, planner)]
    return row


def test_online_summary_csv_columns(fake_online):
    out, rows = fake_online
    with open(out / "summary.csv") as f:
        header = f.readline().strip().split(",")
    assert header == ONLINE_COLUMNS
    assert header[:7] == [*ONLINE_STUDY.keys, "n_seeds", "n_diverged", *ONLINE_STUDY.context]
    for m in ONLINE_STUDY.metrics:  # each metric's columns together, in the order of the metric table
        assert header[header.index(m.columns()[0]) :][: len(m.columns())] == m.columns()
    # against delta: P(final > delta's) and the paired difference (the primary), P(fewer steps to the threshold)
    assert [(m.name, bool(m.versus), bool(m.paired)) for m in ONLINE_STUDY.metrics if m.versus or m.paired] == [
        ("final_reward", True, True),
        ("steps_to_threshold", True, False),
    ]
    assert ONLINE_BASELINE_COLUMNS == [c for m in ONLINE_STUDY.metrics for c in m.baseline_columns()]
    assert not any(c.endswith("_mean") and c.startswith(("final", "auc")) for c in header)  # no mean of rewards
    assert [(r["env"], r["model"]) for r in rows] == [
        ("reacher", "delta"),
        ("reacher", "gem"),
        ("reacher", "gem2"),
        ("hopper", "delta"),
        ("hopper", "gem"),
    ]
    for r in csv_rows(out / "summary.csv"):
        if r["model"] == "delta":
            assert all(r[c] == "" for c in ONLINE_BASELINE_COLUMNS), r


def test_online_diverged_run_is_counted_not_averaged_in(fake_online):
    out, _ = fake_online
    r = online_row(out, "reacher", "gem")
    assert (r["n_seeds"], r["n_diverged"]) == ("4", "1")
    scores = np.array([[fake_finals("gem", s), np.mean(fake_rewards("gem", s))] for s in (0, 1, 3, 4)])
    np.random.seed(0)
    point, interval = library.get_interval_estimates({"x": scores}, rliable_iqm_columns, reps=300)
    assert [float(r[k]) for k in ("final_iqm", "auc_iqm")] == list(point["x"])
    assert [float(r[k]) for k in ("final_ci_low", "auc_ci_low")] == list(interval["x"][0])
    assert [float(r[k]) for k in ("final_ci_high", "auc_ci_high")] == list(interval["x"][1])
    # the cost of the diverged run was spent: the cost means cover every complete run
    assert float(r["wall_time_s_mean"]) == pytest.approx(np.mean([40.0 + s for s in range(5)]), rel=1e-12)
    r = online_row(out, "reacher", "gem2")  # -inf in the last trial: diverged, not a -inf IQM
    assert (r["n_seeds"], r["n_diverged"]) == ("4", "1") and math.isfinite(float(r["final_iqm"]))
    r = online_row(out, "reacher", "delta")  # seed 4 incomplete: missing, not diverged
    assert (r["n_seeds"], r["n_diverged"]) == ("4", "0")
    r = online_row(out, "hopper", "gem")  # every run diverged: no IQM, every final worse than delta's
    assert (r["n_seeds"], r["n_diverged"], r["final_iqm"], r["auc_ci_low"], r["diff_to_delta"]) == (
        "0",
        "2",
        "",
        "",
        "",
    )
    assert float(r["p_improvement"]) == 0.0 and r["n_pairs"] == "0"
    runs = {(r["env"], r["model"], r["seed"]): r for r in csv_rows(out / "summary_runs.csv")}
    assert runs["reacher", "gem", "2"]["diverged"] == "episode_reward nan at trial 1"
    assert runs["reacher", "gem2", "0"]["diverged"] == "episode_reward -inf at trial 3"
    assert runs["reacher", "gem", "3"]["diverged"] == "" and len(runs) == 14 + 4


def test_a_damaged_divergence_record_still_counts_its_run_as_diverged(tmp_path):
    """A run's diverged.txt holding bytes that are not text (a damaged disk) stopped pets.compare online with a
    UnicodeDecodeError traceback, before its runs and in its summary; the file's presence is the record: the run is
    counted diverged, with the readable part of its reason."""
    for seed in range(2):
        fake_run(tmp_path, "reacher", "delta", seed, fake_rewards("delta", seed))
        fake_run(tmp_path, "reacher", "gem", seed, fake_rewards("gem", seed)[: 2 if seed == 0 else FAKE_TRIALS])
    run = tmp_path / "runs" / "reacher-gem-s0"
    (run / rundir.DIVERGED_FILE).write_bytes(b"\xff\xfe model training diverged at trial 2\n")
    assert rundir.read_divergence(run).endswith("model training diverged at trial 2")
    summarise_online(tmp_path, ["reacher"], ["delta", "gem"], range(2), FAKE_TRIALS, FAKE_WINDOW, reps=50)
    r = online_row(tmp_path, "reacher", "gem")
    assert (r["n_seeds"], r["n_diverged"]) == ("1", "1")
    runs = {(r["model"], r["seed"]): r for r in csv_rows(tmp_path / "summary_runs.csv")}
    assert runs["gem", "0"]["diverged"].endswith("model training diverged at trial 2")


def test_online_p_improvement_higher_reward_wins_and_paired_differences(fake_online):
    out, _ = fake_online
    delta = {s: fake_finals("delta", s) for s in range(4)}
    for model, bad in (("gem", 2), ("gem2", 0)):
        r = online_row(out, "reacher", model)
        x = np.array([-math.inf if s == bad else fake_finals(model, s) for s in range(5)])
        p = metrics.probability_of_improvement(x[:, None], np.array(list(delta.values()))[:, None])
        assert float(r["p_improvement"]) == pytest.approx(p, abs=1e-15)
        low, high = float(r["p_improvement_ci_low"]), float(r["p_improvement_ci_high"])
        assert 0 <= low <= float(r["p_improvement"]) <= high <= 1
        diffs = np.array([fake_finals(model, s) - delta[s] for s in range(4) if s != bad])
        assert r["n_pairs"] == str(len(diffs)) == "3"
        np.random.seed(0)
        point, interval = library.get_interval_estimates({"x": diffs[:, None]}, rliable_iqm_columns, reps=300)
        assert float(r["diff_to_delta"]) == point["x"][0]
        assert (float(r["diff_ci_low"]), float(r["diff_ci_high"])) == tuple(interval["x"][:, 0])
    gem, gem2 = online_row(out, "reacher", "gem"), online_row(out, "reacher", "gem2")
    # gem's rewards are higher than delta's, gem2's lower: higher reward is better
    assert float(gem["p_improvement"]) > 0.5 > float(gem2["p_improvement"])
    assert float(gem["diff_to_delta"]) > 0 > float(gem2["diff_to_delta"])


def test_online_exact_paired_p_counts_diverged_runs_as_worst_and_holm_adjusts_over_the_summary(fake_online):
    from statsmodels.stats.multitest import multipletests

    out, _ = fake_online
    diverged_or_missing = {("gem", 2), ("gem2", 0), ("delta", 4)}
    arms = [(m, s) for m in ("delta", "gem", "gem2") for s in range(5) if (m, s) not in diverged_or_missing]
    finite = [fake_finals(m, s) for m, s in arms]
    worst = min(finite)  # a diverged run's final in the exact test: the env's lowest finite final
    raw = {}
    for model, bad in (("gem", 2), ("gem2", 0)):
        diffs = np.array([(worst if s == bad else fake_finals(model, s)) - fake_finals("delta", s) for s in range(4)])
        ref = scipy.stats.permutation_test(
            (diffs, np.zeros_like(diffs)),
            lambda a, b, axis: np.mean(a - b, axis=axis),
            permutation_type="samples",
            n_resamples=np.inf,
        )
        raw[model] = float(online_row(out, "reacher", model)["diff_p_signflip"])
        assert raw[model] == pytest.approx(ref.pvalue, rel=1e-9)
    hopper = online_row(out, "hopper", "gem")  # both runs diverged: both the worst final, an exact test still
    assert float(hopper["diff_p_signflip"]) > 0
    family = [raw["gem"], raw["gem2"], float(hopper["diff_p_signflip"])]
    adjusted = multipletests(family, method="holm")[1]
    got = [
        float(online_row(out, e, m)["diff_p_holm"])
        for e, m in (("reacher", "gem"), ("reacher", "gem2"), ("hopper", "gem"))
    ]
    np.testing.assert_allclose(got, adjusted, rtol=1e-12)
    assert online_row(out, "reacher", "delta")["diff_p_signflip"] == ""
    # the note where the paired difference's bootstrap CI and the exact p disagree, in the CSV and in summary.md
    notes = []
    for model in ("gem", "gem2"):
        r = online_row(out, "reacher", model)
        low, high, p = float(r["diff_ci_low"]), float(r["diff_ci_high"]), float(r["diff_p_signflip"])
        assert r["ci_exact_note"] == ci_exact_note(low, high, 0.0, p)
        notes += [f"reacher / {model}: {r['ci_exact_note']}"] if r["ci_exact_note"] else []
    assert notes  # 3 pairs: the exact p is at least 0.25, while a bootstrap CI of 3 pairs is their min-max
    md = (out / "summary.md").read_text()
    assert all(note in md for note in notes) and "Where the bootstrap CI and the exact test disagree" in md


def test_online_summary_md_has_iqm_p_and_no_nan_or_inf(fake_online):
    out, _ = fake_online
    md = (out / "summary.md").read_text()
    tables = "\n".join(line for line in md.splitlines() if line.startswith("|"))
    assert not re.search(r"\b(nan|inf|None)\b", tables, re.I), "a non-finite or missing number reached a table"
    assert (
        "| model | seeds | diverged | final reward | AUC | P(final > delta's) | final - delta | pairs | p (sign-flip) "
        "| p (Holm) |" in md
    )
    assert "stratified-bootstrap CI" in md and "all diverged" in md
    gem = online_row(out, "reacher", "gem")
    assert (
        f"| gem | 4 | 1 | {fmt_interval(*(float(gem[k]) for k in ('final_iqm', 'final_ci_low', 'final_ci_high')))} |"
        in md
    )
    assert "| delta | 4 | 0 |" in md and "| - | - | - | - | - |" in md
    assert "- reacher-gem-s2: episode_reward nan at trial 1" in md and "- reacher-delta-s4 (2/4 trials)" in md
    sections = dict(re.findall(r"^## (\w+)\n(.*?)(?=^## )", md, re.S | re.M))
    assert "Fewer than 5 seeds cannot carry a claim" in sections["reacher"]  # 4 seeds left
    assert "Fewer than 5 seeds cannot carry a claim" in sections["hopper"]
    for name in ("rewards_reacher.png", "walltime_reacher.png", "rewards_hopper.png"):
        assert (out / name).stat().st_size > 10_000


def test_online_time_to_threshold_counts_runs_that_never_reach_it(tmp_path):
    """Issue 13: minutes (wall_time_s / 60 at the end of the first trial at or above the threshold) and env steps
    to the threshold; the IQM [CI] over the runs that reached it, the others counted in n_reached."""
    from pets.experiments.studies.online import THRESHOLDS, time_to_threshold

    assert THRESHOLDS["invertedpendulum"] == 1000 and THRESHOLDS["reacher"] == -5 and "halfcheetah" in THRESHOLDS
    for model in ("delta", "gem"):
        for seed in range(5):
            fake_run(tmp_path, "reacher", model, seed, fake_rewards(model, seed), cpu=True)
            fake_run(tmp_path, "hopper", model, seed, fake_rewards(model, seed))
    # delta: 10 t + seed reaches 22 in trial 2 for seeds 2-4, trial 3 for seeds 0-1; gem (23 + 1.5 seed) in trial 2
    summarise_online(
        tmp_path, ["reacher", "hopper"], ["delta", "gem"], range(5), FAKE_TRIALS, FAKE_WINDOW, reps=200,
        thresholds={"reacher": 22.0, "hopper": 1000.0},
    )  # fmt: skip
    runs = {(r["env"], r["model"], r["seed"]): r for r in csv_rows(tmp_path / "summary_runs.csv")}
    expected = {s: (3 if s < 2 else 2) for s in range(5)}  # delta's trial index that first reaches 22
    for s, t in expected.items():
        r = runs["reacher", "delta", str(s)]
        assert float(r["minutes_to_threshold"]) == (10.0 * (t + 1) + s) / 60
        assert float(r["steps_to_threshold"]) == 100 * (t + 1)
        assert float(r["cpu_minutes_to_threshold"]) == (5.0 * (t + 1) + s) / 60
        assert runs["hopper", "delta", str(s)]["minutes_to_threshold"] == ""  # never reached: no number
        assert runs["hopper", "delta", str(s)]["cpu_time_s"] == ""  # a run made before the CPU column
    r = online_row(tmp_path, "reacher", "delta")
    assert (r["threshold"], r["n_reached"]) == ("22.0", "5")
    times = np.array(
        [[(10.0 * (t + 1) + s) / 60, 100.0 * (t + 1), (5.0 * (t + 1) + s) / 60] for s, t in expected.items()]
    )
    np.random.seed(0)
    point, interval = library.get_interval_estimates({"x": times}, rliable_iqm_columns, reps=200)
    keys = ("minutes_to_threshold", "steps_to_threshold", "cpu_minutes_to_threshold")
    assert [float(r[f"{k}_iqm"]) for k in keys] == list(point["x"])
    assert [float(r[f"{k}_ci_low"]) for k in keys] == list(interval["x"][0])
    assert float(r["cpu_time_s_mean"]) == np.mean([5.0 * FAKE_TRIALS + s for s in range(5)])
    r = online_row(tmp_path, "hopper", "gem")  # nobody reached 1000: counted, no IQM
    assert (r["n_seeds"], r["n_reached"], r["minutes_to_threshold_iqm"], r["steps_to_threshold_ci_high"]) == (
        "5",
        "0",
        "",
        "",
    )
    # P(gem needs fewer env steps than delta), from rliable on the runs' steps (never reached: the most)
    steps = {
        m: np.array([float(runs["reacher", m, str(s)]["steps_to_threshold"]) for s in range(5)])
        for m in ("gem", "delta")
    }
    expected_p = metrics.probability_of_improvement(-steps["gem"][:, None], -steps["delta"][:, None])
    assert float(online_row(tmp_path, "reacher", "gem")["p_fewer_steps"]) == pytest.approx(expected_p)
    assert expected_p > 0.5 and online_row(tmp_path, "reacher", "delta")["p_fewer_steps"] == ""
    assert online_row(tmp_path, "hopper", "gem")["p_fewer_steps"] == ""  # neither reached it: not measured
    md = (tmp_path / "summary.md").read_text()
    assert "| reached 22 | minutes to it | env steps to it | CPU minutes to it | P(fewer steps than delta) |" in md
    assert "| 0/5 | - | - | - | - |" in md  # P(fewer steps) not measured where neither arm reached it
    assert "| 5/5 | " + fmt_interval(*(float(r2) for r2 in times_iqm(online_row(tmp_path, "reacher", "delta")))) in md
    # the function itself: the first trial at or above, NaN without one or without a threshold
    rewards = [1, 5, 3, 7]
    rows = [
        {"episode_reward": v, "wall_time_s": 60.0 * (i + 1), "env_steps": 10 * (i + 1), "cpu_time_s": 30.0 * (i + 1)}
        for i, v in enumerate(rewards)
    ]
    expected = {"minutes_to_threshold": 2.0, "steps_to_threshold": 20.0, "cpu_minutes_to_threshold": 1.0}
    assert time_to_threshold(rows, 5.0) == expected
    for never in (time_to_threshold(rows, 8.0), time_to_threshold(rows, None)):
        assert list(never) == list(expected) and all(math.isnan(x) for x in never.values())


def times_iqm(row):
    return [row[f"minutes_to_threshold_{k}"] for k in ("iqm", "ci_low", "ci_high")]


def test_online_baseline_is_delta_with_the_same_planner_and_absent_without_delta(tmp_path):
    for model in ("delta", "gem"):
        for planner in ("cem", "icem"):
            for seed in range(5):
                fake_run(tmp_path, "reacher", model, seed, fake_rewards(model, seed, planner), planner)
    summarise_online(
        tmp_path, ["reacher"], ["delta", "gem"], range(5), FAKE_TRIALS, FAKE_WINDOW, planners=["cem", "icem"], reps=50
    )
    for planner in ("cem", "icem"):
        r = online_row(tmp_path, "reacher", "gem", planner)
        # against delta with the same planner: gem+icem against delta+cem would be 1 (icem adds 5 to every reward)
        gem, delta = ([fake_finals(m, s, planner) for s in range(5)] for m in ("gem", "delta"))
        p = metrics.probability_of_improvement(np.array(gem)[:, None], np.array(delta)[:, None])
        assert float(r["p_improvement"]) == pytest.approx(p, abs=1e-15) and p == pytest.approx(0.94)
        diffs = [g - d for g, d in zip(gem, delta)]  # 3 + 0.5 seed: the IQM of 5 is the mean of the middle 3
        assert float(r["diff_to_delta"]) == pytest.approx(np.mean(diffs[1:4]), rel=1e-12)
        assert all(online_row(tmp_path, "reacher", "delta", planner)[c] == "" for c in ONLINE_BASELINE_COLUMNS)
    md = (tmp_path / "summary.md").read_text()
    assert "| model | planner | seeds |" in md and "Fewer than 5" not in md
    rows = summarise_online(
        tmp_path, ["reacher"], ["gem"], range(5), FAKE_TRIALS, FAKE_WINDOW, planners=["cem"], reps=50
    )
    assert [r["p_improvement"] for r in rows] == [None]
    assert all(online_row(tmp_path, "reacher", "gem", "cem")[c] == "" for c in ONLINE_BASELINE_COLUMNS)
    assert "P(final" not in (tmp_path / "summary.md").read_text()


def test_openloop_on_an_online_run_replays_in_the_simulator(online, tmp_path, capsys):
    out, _ = online
    run = out / "runs" / "invertedpendulum-gem-s1"
    path = tmp_path / "ol.json"
    with one_thread():
        code = openloop.main(
            [
                "--run",
                str(run),
                "--steps",
                "6",
                "--episodes",
                "3",
                "--seed",
                "4",
                "--device",
                "cpu",
                "--json",
                str(path),
                "--quiet",
                "planner.population=12",
            ]
        )
    printed = capsys.readouterr().out
    assert code == 0 and "total reward" in printed and "open loop: invertedpendulum / gem / cem" in printed
    res = json.loads(path.read_text())
    assert res["planner_config"]["horizon"] == 6 and res["planner_config"]["population"] == 12
    assert res["planner_config"]["particles"] == 2  # the run's own setting
    check_open_loop_result(res, "invertedpendulum", steps=6, episodes=3)


# --------------------------------------------------------------------------- open loop (ground truth)
def check_open_loop_result(res, env, steps, episodes):
    """Structure of an open-loop result, and its rewards equal the simulator's for the planned actions."""
    assert {
        "run",
        "env",
        "model",
        "planner",
        "steps",
        "episodes",
        "seed",
        "reward_per_step",
        "total",
        "mean_reward_per_step",
        "rewards",
        "actions",
        "lengths",
        "terminated",
        "reset_seeds",
        "predicted_return",
        "planner_config",
    } <= set(res)
    assert res["env"] == env and res["steps"] == steps and res["episodes"] == episodes
    spec = envs.get(env)
    rewards, actions = np.array(res["rewards"]), np.array(res["actions"])
    assert rewards.shape == (episodes, steps) and actions.shape == (episodes, steps, spec.act_dim)
    assert (actions >= np.array(spec.action_low)).all() and (actions <= np.array(spec.action_high)).all()
    sim = spec.make()
    for i in range(episodes):
        sim.reset(seed=res["reset_seeds"][i])
        length = res["lengths"][i]
        for t in range(length):
            _, r, term, _, _ = sim.step(actions[i, t])
            assert rewards[i, t] == r
            assert term == (res["terminated"][i] and t == length - 1)
        assert (rewards[i, length:] == 0).all()  # nothing executed after a real termination
        assert length == steps or res["terminated"][i]
    sim.close()
    np.testing.assert_allclose(res["reward_per_step"]["mean"], rewards.mean(axis=0))
    assert len(res["reward_per_step"]["ci_low"]) == steps
    np.testing.assert_allclose(res["total"]["values"], rewards.sum(axis=1))
    assert res["total"]["mean"] == pytest.approx(rewards.sum(axis=1).mean())
    assert res["mean_reward_per_step"]["mean"] == pytest.approx(rewards.sum(axis=1).mean() / steps)
    assert len(res["predicted_return"]) == episodes and all(math.isfinite(v) for v in res["predicted_return"])


# --------------------------------------------------------------------------- offline
OFFLINE_ARGS = [
    "offline",
    "--envs",
    "invertedpendulum",
    "--models",
    "delta,gem",
    "--seeds",
    "0,1",
    "--episodes",
    8,
    "--test-episodes",
    4,
    "--horizons",
    "1,3,5",
    "--starts",
    20,
    "--openloop",
    "--planners",
    "cem,mppi",
    "--openloop-steps",
    12,
    "--openloop-episodes",
    2,
    "--preset",
    "fast",
    "--device",
    "cpu",
    "--quiet",
    *TINY_OFFLINE,
]


@pytest.fixture(scope="module")
def offline(tmp_path_factory):
    out = tmp_path_factory.mktemp("offline")
    result = compare_offline(
        ["invertedpendulum"],
        ["delta", "gem"],
        [0, 1],
        out,
        episodes=8,
        test_episodes=4,
        horizons=[1, 3, 5],
        starts=20,
        openloop=True,
        planners=["cem", "mppi"],
        openloop_steps=12,
        openloop_episodes=2,
        preset="fast",
        device="cpu",
        overrides=TINY_OFFLINE,
        progress=False,
    )
    return out, result


def test_summary_from_the_runs_csv_equals_the_studys_own(offline, tmp_path, capsys):
    """summary_from_runs (for committed studies whose run directories are gone) recomputes the study's summary.csv
    and relative_error.csv, every cell, from its prediction_runs.csv at the study's no-information level; the
    script around it writes them and counts what moved."""
    out, _ = offline
    level = float(csv_rows(out / "primary.csv")[0]["level"])
    summary, relative = summary_from_runs(csv_rows(out / "prediction_runs.csv"), level)
    write_csv(tmp_path / "summary.csv", summary, SUMMARY_COLUMNS)
    assert csv_rows(tmp_path / "summary.csv") == csv_rows(out / "summary.csv")
    rel_columns = list(csv_rows(out / "relative_error.csv")[0])
    write_csv(tmp_path / "relative_error.csv", relative, rel_columns)
    assert csv_rows(tmp_path / "relative_error.csv") == csv_rows(out / "relative_error.csv")
    (tmp_path / "s_summary.csv").write_bytes((out / "summary.csv").read_bytes())
    script = _script("resummarise_offline")
    args = [str(out / "prediction_runs.csv"), "--out", str(tmp_path / "s"), "--level"]
    assert script.main([*args, repr(level)]) == 0
    assert "values changed against the file before: none" in capsys.readouterr().out
    assert script.main([*args, "1e-9"]) == 0
    assert "n_diverged" in capsys.readouterr().out  # every run past a level of ~0: the counts move, and it says so


def test_offline_writes_data_runs_and_summaries(offline):
    out, result = offline
    assert result["failed"] == {} and result["data"] == {
        "invertedpendulum-train.npz": "collected",
        "invertedpendulum-test.npz": "collected",
    }
    assert all(done == ["train", "eval", "openloop_cem", "openloop_mppi"] for done in result["done"].values())
    for name in (
        "prediction.md",
        "summary.csv",
        "relative_error.csv",
        "prediction_runs.csv",
        "relative_error.png",
        "ratio_to_delta.png",
        "absolute_error_invertedpendulum.png",
        "openloop.md",
        "openloop.csv",
        "openloop_invertedpendulum.png",
    ):
        assert (out / name).is_file() and (out / name).stat().st_size > 100, name
    train, test = (np.load(out / "data" / f"invertedpendulum-{p}.npz") for p in ("train", "test"))
    assert int(train["seed"]) == 0 and int(test["seed"]) == 1 and len(train["lengths"]) == 8
    assert not np.array_equal(train["obs"][:4, 0], test["obs"][:, 0])  # separate data sets


def test_offline_runs_hold_their_per_horizon_errors_as_tensorboard_events(offline):
    """Issue 15: eval/METRIC at step = horizon, read back with TensorBoard's reader, equal to eval.json."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, _ = offline
    run_dir = out / "runs" / "invertedpendulum-gem-s1"
    result = json.loads((run_dir / "eval.json").read_text())
    events = EventAccumulator(str(run_dir / "eval" / "invertedpendulum-test")).Reload()
    scalars = {e.step: e.value for e in events.Scalars("eval/mean_step_error")}
    want = {int(h): row["mean_step_error"] for h, row in result["horizons"].items()}
    assert len(scalars) == 3 and scalars == pytest.approx(want, rel=1e-6)


def test_offline_summary_csv_equals_the_runs_evaluations(offline):
    out, _ = offline
    rows = [r for r in csv_rows(out / "summary.csv") if r["metric"] == "mean_step_error"]
    assert {(r["model"], r["horizon"]) for r in rows} == {(m, h) for m in ("delta", "gem") for h in ("1", "3", "5")}
    evals = {
        (m, s): json.loads((out / "runs" / f"invertedpendulum-{m}-s{s}" / "eval.json").read_text())
        for m in ("delta", "gem")
        for s in (0, 1)
    }
    assert all(e["model"] == m and e["env"] == "invertedpendulum" for (m, _), e in evals.items())
    assert evals["delta", 0]["start_points"] == evals["gem", 1]["start_points"]  # paired: the same starts everywhere
    assert all(e["standardized_by"] == str(out / "data" / "invertedpendulum-train.npz") for e in evals.values())
    for r in rows:
        values = [evals[r["model"], s]["horizons"][r["horizon"]]["mean_step_error"] for s in (0, 1)]
        assert int(r["n_seeds"]) == 2 and int(r["n_diverged"]) == 0  # the tiny models do not diverge in 5 steps
        # two seeds: the IQM is the mean, and the bootstrap CI is [min, max]
        assert float(r["iqm"]) == pytest.approx(np.mean(values), rel=1e-12)
        assert (float(r["ci_low"]), float(r["ci_high"])) == (min(values), max(values))
        if r["model"] == "delta":
            assert r["p_improvement"] == r["ratio_to_delta"] == ""
        else:
            deltas = [evals["delta", s]["horizons"][r["horizon"]]["mean_step_error"] for s in (0, 1)]
            p = metrics.probability_of_improvement(-np.array(values)[:, None], -np.array(deltas)[:, None])
            assert float(r["p_improvement"]) == p
            assert float(r["ratio_to_delta"]) == pytest.approx(np.mean(np.divide(values, deltas)), rel=1e-12)
    averaged = {  # Fig. 2: per seed the mean over horizons, then the IQM over seeds (n = 2: the mean)
        m: np.mean([np.mean([evals[m, s]["horizons"][h]["mean_step_error"] for h in ("1", "3", "5")]) for s in (0, 1)])
        for m in ("delta", "gem")
    }
    top = max(averaged.values())
    relative = {r["model"]: r for r in csv_rows(out / "relative_error.csv") if r["metric"] == "mean_step_error"}
    for m in ("delta", "gem"):
        assert float(relative[m]["relative"]) == pytest.approx(averaged[m] / top, rel=1e-12)
    md = (out / "prediction.md").read_text()
    assert re.search(r"^\| invertedpendulum \| 1 3 5 \| gem \| 2 \| 0 \| ", md, re.M)  # tracked at every horizon
    primary = {r["model"]: r for r in csv_rows(out / "primary.csv")}  # Fig. 2 averages over the primary's horizons
    assert {r["horizons"] for r in csv_rows(out / "relative_error.csv")} == {primary["delta"]["tracking_horizons"]}
    assert "Fewer than 5 seeds cannot carry a claim" in md


def test_offline_open_loop_results_replay_in_the_simulator(offline):
    out, _ = offline
    terminated = 0
    table = {(r["planner"], r["model"]): r for r in csv_rows(out / "openloop.csv")}
    assert set(table) == {(p, m) for p in ("cem", "mppi") for m in ("delta", "gem")}
    for planner in ("cem", "mppi"):
        for model in ("delta", "gem"):
            results = [
                json.loads((out / "runs" / f"invertedpendulum-{model}-s{s}" / f"openloop_{planner}.json").read_text())
                for s in (0, 1)
            ]
            for res in results:
                assert res["planner"] == planner and res["model"] == model
                check_open_loop_result(res, "invertedpendulum", steps=12, episodes=2)
                terminated += sum(res["terminated"])
            row = table[(planner, model)]
            assert float(row["reward_per_step_mean"]) == pytest.approx(
                np.mean([r["mean_reward_per_step"]["mean"] for r in results]), rel=1e-12
            )
    assert terminated > 0  # 12 open-loop steps of a barely trained model: the pendulum falls somewhere


def test_offline_rerun_reuses_and_new_horizons_only_re_evaluate(offline, capsys):
    out, _ = offline
    runs = sorted((out / "runs").iterdir())
    before = {d.name: {f.name: f.stat().st_mtime_ns for f in d.iterdir()} for d in runs}
    code, stdout, stderr = cli(capsys, *OFFLINE_ARGS, "--out", out)
    assert code == 0 and "4 runs: 4 reused, 0 with work to do" in stderr and "## invertedpendulum" in stdout
    assert stderr.count("fewer than 5 seeds cannot carry a claim") == 1  # --seeds 0,1
    assert {d.name: {f.name: f.stat().st_mtime_ns for f in d.iterdir()} for d in runs} == before
    args = [a if a != "1,3,5" else "1,2" for a in OFFLINE_ARGS]
    code, _, stderr = cli(capsys, *args, "--out", out)
    assert code == 0 and "4 reused" not in stderr
    for d in runs:  # evaluated again, not trained again, open loop untouched
        assert d.joinpath("checkpoint.pt").stat().st_mtime_ns == before[d.name]["checkpoint.pt"]
        assert d.joinpath("openloop_cem.json").stat().st_mtime_ns == before[d.name]["openloop_cem.json"]
        assert list(json.loads(d.joinpath("eval.json").read_text())["horizons"]) == ["1", "2"]
    assert {r["horizon"] for r in csv_rows(out / "summary.csv")} == {"1", "2"}


def test_offline_refuses_other_data_or_config_in_the_same_directory(offline, capsys):
    out, _ = offline
    args = [a if a != 8 else 9 for a in OFFLINE_ARGS]  # --episodes 9
    code, _, err = cli(capsys, *args, "--out", out)
    assert code == 2 and "collected with other settings (episodes: 8 != 9)" in err
    wider = [a if a != "model.hidden_size=32" else "model.hidden_size=64" for a in OFFLINE_ARGS]
    code, _, err = cli(capsys, *wider, "--out", out)
    assert code == 2 and "model.hidden_size: 32 != 64" in err and len(err.strip().splitlines()) == 1


def test_offline_existing_policy_takes_the_data_files_as_they_are(offline, tmp_path, capsys):
    out = tmp_path / "sweep"  # a copy: its new horizons would leave the shared sweep's runs work to do
    shutil.copytree(offline[0], out)
    result = compare_offline(
        ["invertedpendulum"],
        ["delta"],
        [0],
        out,
        episodes=1,
        test_episodes=1,
        policy="existing",
        horizons=[1, 2],
        starts=20,
        preset="fast",
        device="cpu",
        overrides=TINY_OFFLINE,
        progress=False,
    )
    assert result["data"] == {"invertedpendulum-train.npz": "reused", "invertedpendulum-test.npz": "reused"}
    assert result["failed"] == {} and all("train" not in todo for todo in result["todo"].values())
    code, _, err = cli(
        capsys, "offline", "--envs", "reacher", "--models", "delta", "--policy", "existing", "--out", tmp_path / "new"
    )
    assert code == 2 and "--policy existing needs the data file" in err


def test_offline_data_collected_as_backend_jobs_and_a_failed_env_fails_only_its_runs(tmp_path, monkeypatch, capsys):
    """Missing data sets are jobs of the backend (one per env); an env whose collection fails fails its runs with the
    reason ("no data: ..."), the other env's runs go on; the status line counts them as such (was: as reused)."""
    import pets.data.collect

    real = pets.data.collect.collect

    def collect(spec, *args, **kwargs):
        if spec.name == "reacher":
            raise RuntimeError("simulated collection failure")
        return real(spec, *args, **kwargs)

    monkeypatch.setattr(pets.data.collect, "collect", collect)
    result = compare_offline(
        ["invertedpendulum", "reacher"],
        ["delta"],
        [0],
        tmp_path,
        episodes=2,
        test_episodes=1,
        horizons=[1, 2],
        starts=10,
        preset="fast",
        device="cpu",
        overrides=TINY_OFFLINE,
        progress=False,
    )
    assert result["data"] == {"invertedpendulum-train.npz": "collected", "invertedpendulum-test.npz": "collected"}
    assert result["failed"] == {"reacher-delta-s0": "no data: RuntimeError: simulated collection failure"}
    assert result["done"] == {"invertedpendulum-delta-s0": ["train", "eval"]}
    assert not (tmp_path / "data" / "reacher-train.npz").exists()
    assert "2 runs: 0 reused, 1 with work to do, 1 without their data set (failed) (" in capsys.readouterr().err


def test_online_runs_start_seed_major_so_a_sweep_cut_short_is_paired(tmp_path, monkeypatch):
    """Every arm of the first seed is handed to the backend before any run of the next seed."""
    import contextlib

    from pets.experiments import online

    handed: list[str] = []

    @contextlib.contextmanager
    def recording_backend(backend, out, needed=True):
        def run(jobs, *, processes, progress, desc):
            handed.extend(name for name, _, _ in jobs)
            return {name: (False, "not run (test)") for name, _, _ in jobs}

        yield run

    monkeypatch.setattr(online, "open_backend", recording_backend)
    online.compare_online(["reacher"], ["delta", "gem"], [0, 1, 2], 2, tmp_path, preset="fast", progress=False)
    assert handed == [f"reacher-{m}-s{s}" for s in (0, 1, 2) for m in ("delta", "gem")]


def test_overrides_anywhere_on_the_line_and_cuda_refused_up_front(tmp_path, monkeypatch, capsys):
    """Issue 34: a key=value after another option's value was "unrecognized arguments" (exit 2) although the key is
    valid; --device cuda on a machine without CUDA launched every run to fail. Now the override is taken wherever
    it stands (here an unknown key proves it reached the config check), and CUDA is refused before any work."""
    import torch

    base = ["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "--preset", "fast"]
    code, _, err = cli(capsys, *base, "--seeds", 0, "planner.nope=1", "--out", tmp_path / "a")
    assert code == 2 and "unknown config key 'planner.nope'" in err and not (tmp_path / "a").exists()
    code, _, err = cli(capsys, *base, "--seeds", 0, "--bogus", "--out", tmp_path / "a")
    assert code == 2 and "unrecognized arguments: --bogus" in err
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for device in (["--device", "cuda"], ["device=cuda"]):
        code, _, err = cli(capsys, *base, "--seeds", 0, "--out", tmp_path / "b", *device)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and "torch sees no CUDA device" in lines[0], err
        assert not (tmp_path / "b").exists()


def test_a_repeated_override_in_one_value_is_taken_threads_too(tmp_path, capsys):
    """threads=2 threads=2 (and threads=2 threads=02) is one value, as a repeat of any other key is
    (planner.horizon=5 planner.horizon=05): each run gets 2 threads; threads=2 threads=3 is refused in one line, as
    --threads 2 threads=2 is (the option and the key, not both)."""
    from pets.experiments.options import build_parser

    base = ["online", "--envs", "reacher", "--models", "delta", "--seeds", "0", "--trials", "1", "--preset", "fast"]
    base += ["--out", str(tmp_path / "a")]
    for repeat in (["threads=2", "threads=2"], ["threads=2", "threads=02"]):
        assert cli_module._parse(build_parser(), [*base, *repeat]).threads == 2
        code, out, err = cli(capsys, *base, "--print-config", *repeat, "planner.horizon=5", "planner.horizon=05")
        assert code == 0 and "  horizon: 5\n" in out, err
    for refused, line in (
        (["threads=2", "threads=3"], "threads is given twice (threads=2 and threads=3); give it once"),
        (["threads=2", "--threads", "2"], "give the threads once: --threads N or threads=N, not both"),
    ):
        code, _, err = cli(capsys, *base, *refused)
        assert code == 2 and len(err.strip().splitlines()) == 1 and line in err, err
    assert not (tmp_path / "a").exists()


def test_a_file_or_other_files_where_a_run_directory_is_made_are_refused_before_any_run(tmp_path, capsys):
    """OUT/runs/ENV-MODEL-sSEED that is a file (or OUT/runs that is), or a folder of other files, is exit 2 and one
    line naming it before any run starts (the run failed as it started, exit 3, after the runs before it)."""
    out = tmp_path / "cmp"
    base = ["online", "--envs", "invertedpendulum", "--models", "gem,delta", "--seeds", "0", "--trials", "1", "--out",
            out, "--preset", "fast", "--quiet", *TINY]  # fmt: skip
    run = out / "runs" / "invertedpendulum-delta-s0"
    run.parent.mkdir(parents=True)
    run.write_text("not a run\n")
    code, _, err = cli(capsys, *base)
    lines = err.strip().splitlines()
    assert code == 2 and lines == [f"pets.compare: error: {run} is a file, not the run directory of a run to start; "
                                   "move or delete it"]  # fmt: skip
    run.unlink()
    run.mkdir()
    (run / "notes.txt").write_text("mine\n")
    code, _, err = cli(capsys, *base)
    assert code == 2 and f"{run} is not empty and holds no run (notes.txt)" in err and len(err.splitlines()) == 1
    shutil.rmtree(out / "runs")
    (out / "runs").write_text("not a folder\n")
    code, _, err = cli(capsys, *base)
    assert code == 2 and f"{out / 'runs'} is a file, not the folder of the run directories" in err
    assert sorted(p.name for p in out.iterdir()) == ["runs"]  # no log, lock or summary: nothing ran


def test_online_refuses_an_offline_run_directory(offline, capsys):
    out, _ = offline  # same config as the offline runs (trials aside): only the run kind differs
    code, _, err = cli(
        capsys,
        "online",
        "--envs",
        "invertedpendulum",
        "--models",
        "delta",
        "--seeds",
        0,
        "--trials",
        1,
        "--out",
        out,
        "--preset",
        "fast",
        "--device",
        "cpu",
        *TINY_OFFLINE,
        "model.patience=20",
    )
    assert code == 2 and "is an offline training run" in err


def test_offline_refuses_an_online_run_directory_whatever_its_config(tmp_path, capsys):
    """The other way round: an online comparison's --out given to an offline one with the same settings was taken
    as its own (the online model evaluated as if trained on the offline data, the online summary replaced)."""
    run = tmp_path / "runs" / "invertedpendulum-delta-s0"
    run.mkdir(parents=True)
    rundir.write_config(run, make_config("invertedpendulum", "delta", "fast", {"seed": 0}))
    (run / "history.csv").write_text("time,action,trials_done,host,pid\n")
    (tmp_path / "summary.csv").write_text("the online summary\n")
    args = ["offline", "--envs", "invertedpendulum", "--models", "delta", "--seeds", 0, "--preset", "fast"]
    code, _, err = cli(capsys, *args, "--episodes", 2, "--out", tmp_path, *TINY_OFFLINE)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "is an online run (run_pets.py), not an offline one" in lines[0], err
    assert (tmp_path / "summary.csv").read_text() == "the online summary\n" and not (tmp_path / "data").exists()


def test_offline_refuses_a_run_or_data_path_it_cannot_use_before_any_work(tmp_path, capsys):
    """As online: OUT/runs/ENV-MODEL-sSEED that is a file (or OUT/runs is), or a folder of other files, and OUT/data
    that is a file or a data file that is a folder, are exit 2 and one line naming them before any data is collected
    or run trained (each failed as its job started, exit 3 with an OSError, and the sweep went on)."""
    out = tmp_path / "off"
    base = ["offline", "--envs", "invertedpendulum", "--models", "delta", "--seeds", 0, "--episodes", 2, "--out", out,
            "--preset", "fast", "--device", "cpu", "--quiet", *TINY_OFFLINE]  # fmt: skip
    run, data = out / "runs" / "invertedpendulum-delta-s0", out / "data"
    cases = [
        (run, "file", f"{run} is a file, not the run directory of a run to start; move or delete it"),
        (run.parent, "file", f"{run.parent} is a file, not the folder of the run directories; move or delete it"),
        (run / "notes.txt", "file", f"{run} is not empty and holds no run (notes.txt)"),
        (data, "file", f"{data} is a file, not the folder of the data sets; move or delete it"),
        (data / "invertedpendulum-test.npz", "dir", f"{data / 'invertedpendulum-test.npz'} is a directory, not a data"),
    ]
    for path, kind, message in cases:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.mkdir() if kind == "dir" else path.write_text("mine\n")
        code, _, err = cli(capsys, *base)
        assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, (path, err)
        assert {p.relative_to(out) for p in out.rglob("*")} == {p.relative_to(out) for p in [*path.parents, path]
                                                                if out in p.parents}, path  # fmt: skip
        shutil.rmtree(out)


def one_offline_run(tmp_path, capsys):
    """``(args, run directory)`` of a tiny offline sweep of one run, made with ``pets.compare ARGS``."""
    out = tmp_path / "off"
    args = ["offline", "--envs", "invertedpendulum", "--models", "delta", "--seeds", 0, "--episodes", 3,
            "--test-episodes", 2, "--horizons", "1,3", "--starts", 10, "--out", out, "--preset", "fast", "--device",
            "cpu", "--quiet", *TINY_OFFLINE]  # fmt: skip
    assert cli(capsys, *args)[0] == 0
    return args, out / "runs" / "invertedpendulum-delta-s0"


def test_offline_redoes_a_run_whose_job_was_killed_as_it_wrote_the_run(tmp_path, capsys):
    """A job killed (kill -9) while its training wrote the run leaves the run's files without config.yaml (written
    last): the same command trains that run again, as the module promises, instead of failing it for holding files."""
    args, run = one_offline_run(tmp_path, capsys)
    for name in ("config.yaml", "eval.json", "eval"):  # what the job writes after the training's own files
        shutil.rmtree(run / name) if (run / name).is_dir() else (run / name).unlink()
    assert {"checkpoint.pt", "metrics.csv"} <= {p.name for p in run.iterdir()}
    code, _, err = cli(capsys, *args)
    assert code == 0 and "0 reused, 1 with work to do" in err, err
    assert (run / "config.yaml").is_file() and json.loads((run / "eval.json").read_text())["request"]["starts"] == 10


def test_offline_refuses_a_trained_run_without_its_checkpoint_before_any_work(tmp_path, capsys):
    """A run whose checkpoint.pt is gone (deleted, as a damaged checkpoint's message advises) failed its evaluation at
    every rerun with "no trial completed", an online run's words; it is exit 2, one line saying how to train it
    again, and nothing is written."""
    run = tmp_path / "runs" / "invertedpendulum-delta-s0"
    run.mkdir(parents=True)
    rundir.write_config(run, make_config("invertedpendulum", "delta", "fast", {"seed": 0}))
    args = ["offline", "--envs", "invertedpendulum", "--models", "delta", "--seeds", 0, "--preset", "fast"]
    code, _, err = cli(capsys, *args, "--episodes", 2, "--out", tmp_path, *TINY_OFFLINE)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert f"{run} holds a trained run's config.yaml but no checkpoint.pt" in lines[0] and "delete the run" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"] and [p.name for p in run.iterdir()] == ["config.yaml"]


def test_offline_refuses_a_damaged_checkpoint_it_would_load_before_any_work(tmp_path, capsys):
    """A trained run whose checkpoint.pt is cut off or has bytes changed failed (exit 3) only when its job came, maybe
    hours into a sweep; a run to evaluate or plan with it is exit 2, one line naming the file and what to do, before
    any work. A run reused as it is (its checkpoint not loaded) is not refused."""
    args, run = one_offline_run(tmp_path, capsys)
    checkpoint, whole = run / "checkpoint.pt", (run / "checkpoint.pt").read_bytes()
    evaluation = (run / "eval.json").read_bytes()
    middle = len(whole) // 2
    damaged = {
        "cut off": whole[:middle],
        "changed": whole[:middle] + bytes([whole[middle] ^ 0xFF]) + whole[middle + 1 :],
    }
    new_horizons = [*args[: args.index("--horizons") + 1], "1,2", *args[args.index("--horizons") + 2 :]]
    for kind, data in damaged.items():
        checkpoint.write_bytes(data)
        code, _, err = cli(capsys, *new_horizons)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, (kind, err)
        assert f"{checkpoint} is damaged (" in lines[0] and "delete the run directory to train it again" in lines[0]
        assert (run / "eval.json").read_bytes() == evaluation, kind
        code, _, err = cli(capsys, *args)  # nothing to do with the model: reused
        assert code == 0 and "1 reused, 0 with work to do" in err, (kind, err)
    checkpoint.write_bytes(whole)
    assert cli(capsys, *new_horizons)[0] == 0


# --------------------------------------------------------------------------- offline summary on fake evaluations
FAKE_REQUEST = {"horizons": [1, 5], "starts": 10, "seed": 0, "mode": "mean"}
NEW_KEYS = [  # pets.evaluate's keys after issue 11 (the summary takes whatever *_error keys the files have)
    "mean_step_error",
    "final_step_error",
    "translation_error",
    "rotation_error",
    "velocity_error",
    "other_error",
    "derived_error",
    "standardized_error",
]
SCALE = {"delta": 1.0, "gem": 0.7, "gem2": 1.3}


def fake_eval(out, env, model, seed, horizons):
    """A run directory with only an eval.json for FAKE_REQUEST: ``horizons`` = {h: {key: value}}."""
    run = out / "runs" / f"{env}-{model}-s{seed}"
    run.mkdir(parents=True)
    result = {"request": {**FAKE_REQUEST, "data": f"data/{env}-test.npz"}, "starts": 10, "horizons": horizons}
    (run / "eval.json").write_text(json.dumps({**result, "env": env, "model": model}))


def fake_values(model, seed, h, keys=NEW_KEYS, rotations=True):
    """Distinct error values per model, seed, horizon and key (no ties between models)."""
    values = {k: SCALE[model] * (1 + seed + 0.01 * seed**2) * h * (i + 1) / 10 for i, k in enumerate(keys)}
    if "standardized_error" in values:  # below the no-information level (sqrt(2)): these runs track the state
        values["standardized_error"] /= 100
    if "rotation_error" in values and not rotations:
        values["rotation_error"] = 0.0
    return {**values, "nonfinite_fraction": 0.0}


@pytest.fixture(scope="module")
def fake_offline(tmp_path_factory):
    """reacher: delta, gem, gem2 with 5 seeds; gem seed 4 goes NaN at h=5, gem2 seed 3 has standardized_error 7e4.
    invertedpendulum (no rotations): delta and gem, 3 seeds. hopper: gem diverged in both of its 2 seeds."""
    out = tmp_path_factory.mktemp("fake-offline")
    for model in ("delta", "gem", "gem2"):
        for seed in range(5):
            hs = {str(h): fake_values(model, seed, h) for h in (1, 5)}
            if (model, seed) == ("gem", 4):
                hs["5"]["mean_step_error"], hs["5"]["nonfinite_fraction"] = math.nan, 0.2
            if (model, seed) == ("gem2", 3):
                hs["5"]["standardized_error"], hs["5"]["mean_step_error"] = 7e4, 7e4
            fake_eval(out, "reacher", model, seed, hs)
    for model in ("delta", "gem"):
        for seed in range(3):
            fake_eval(
                out,
                "invertedpendulum",
                model,
                seed,
                {str(h): fake_values(model, seed, h, rotations=False) for h in (1, 5)},
            )
    for seed in range(2):
        fake_eval(out, "hopper", "delta", seed, {str(h): fake_values("delta", seed, h) for h in (1, 5)})
        hs = {str(h): {**fake_values("gem", seed, h), "standardized_error": math.inf} for h in (1, 5)}
        fake_eval(out, "hopper", "gem", seed, hs)
    rows = summarise_offline(
        out, ["reacher", "invertedpendulum", "hopper"], ["delta", "gem", "gem2"], range(5), FAKE_REQUEST, reps=200
    )
    return out, rows


def summary_row(out, env, model, horizon, metric):
    (row,) = [
        r
        for r in csv_rows(out / "summary.csv")
        if (r["env"], r["model"], r["horizon"], r["metric"]) == (env, model, str(horizon), metric)
    ]
    return row


def test_summary_csv_has_every_env_model_horizon_and_metric(fake_offline):
    out, rows = fake_offline
    with open(out / "summary.csv") as f:
        header = f.readline().strip().split(",")
    assert header == SUMMARY_COLUMNS
    assert header[:10] == "env model horizon metric iqm ci_low ci_high n_seeds n_diverged p_improvement".split()
    table = csv_rows(out / "summary.csv")
    assert len(table) == len(rows) == (3 + 2 + 2) * 2 * len(NEW_KEYS)  # (env, model) pairs x horizons x metrics
    assert [r["metric"] for r in table[: len(NEW_KEYS) * 2 : 2]] == NEW_KEYS  # the preferred order
    for r in table:
        if r["model"] == "delta":  # nothing to compare with
            assert all(r[c] == "" for c in SUMMARY_COLUMNS[9:]), r
        elif r["n_seeds"] != "0":
            assert float(r["ci_low"]) <= float(r["iqm"]) <= float(r["ci_high"])
            assert 0 <= float(r["p_improvement_ci_low"]) <= float(r["p_improvement"]) <= 1


def expected_statistics(model, h, diverged_seeds, metric="mean_step_error"):
    """From the fixture's own values: (IQM over the seeds not diverged at h, rliable's P with a diverged seed's
    error +inf, IQM of the ratios to delta over the seeds not diverged at h)."""
    errors = [fake_values(model, s, h)[metric] for s in range(5)]
    deltas = [fake_values("delta", s, h)[metric] for s in range(5)]
    kept = [s for s in range(5) if s not in diverged_seeds]
    iqm = metrics.aggregate_iqm(np.array([errors[s] for s in kept]))
    worst = [math.inf if s in diverged_seeds else errors[s] for s in range(5)]
    p = metrics.probability_of_improvement(-np.array(worst)[:, None], -np.array(deltas)[:, None])
    ratio = metrics.aggregate_iqm(np.array([errors[s] / deltas[s] for s in kept]))
    return iqm, p, ratio


def test_a_run_diverged_at_one_horizon_counts_at_the_others(fake_offline):
    out, _ = fake_offline
    for model, bad in (("gem", 4), ("gem2", 3)):  # diverged at h=5 only
        for h, diverged, counts in ((1, [], ("5", "0", "5")), (5, [bad], ("4", "1", "4"))):
            for metric in ("mean_step_error", "velocity_error"):  # velocity_error is finite at h=5: out all the same
                r = summary_row(out, "reacher", model, h, metric)
                assert (r["n_seeds"], r["n_diverged"], r["n_pairs"]) == counts
                iqm, p, ratio = expected_statistics(model, h, diverged, metric)
                assert float(r["iqm"]) == iqm
                assert float(r["ci_low"]) <= iqm <= float(r["ci_high"])
                assert float(r["p_improvement"]) == pytest.approx(p, abs=1e-15)  # diverged: an infinite error
                assert float(r["ratio_to_delta"]) == pytest.approx(ratio, rel=1e-12)  # seeds neither diverged at
    # the average over the horizons counts only the runs diverged at none of them
    relative = {(r["model"], r["metric"]): r for r in csv_rows(out / "relative_error.csv") if r["env"] == "reacher"}
    for model, bad in (("gem", 4), ("gem2", 3)):
        r = relative[model, "mean_step_error"]
        assert (r["n_seeds"], r["n_diverged"], r["n_pairs"]) == ("4", "1", "4")
        kept = [s for s in range(5) if s != bad]
        averaged = [np.mean([fake_values(model, s, h)["mean_step_error"] for h in (1, 5)]) for s in kept]
        assert float(r["iqm"]) == pytest.approx(metrics.aggregate_iqm(np.array(averaged)), rel=1e-12)
    assert (relative["delta", "mean_step_error"]["n_seeds"], relative["delta", "mean_step_error"]["n_diverged"]) == (
        "5",
        "0",
    )
    for h in (1, 5):  # every run diverged at every horizon: no IQM, P = 0
        r = summary_row(out, "hopper", "gem", h, "mean_step_error")
        assert (r["n_seeds"], r["n_diverged"], r["iqm"], r["ci_low"], r["ratio_to_delta"]) == ("0", "2", "", "", "")
        assert float(r["p_improvement"]) == 0.0 and r["n_pairs"] == "0"


def test_prediction_runs_csv_names_the_divergence_at_its_horizon_only(fake_offline):
    out, _ = fake_offline
    runs = {(r["env"], r["model"], r["seed"], r["horizon"]): r for r in csv_rows(out / "prediction_runs.csv")}
    assert runs["reacher", "gem2", "3", "5"]["diverged"] == "standardized_error 7e+04 >= the no-information level 1.41"
    assert runs["reacher", "gem", "4", "5"]["diverged"] == "mean_step_error nan"
    for run in (("gem2", "3"), ("gem", "4"), ("gem", "3")):
        assert runs[("reacher", *run, "1")]["diverged"] == ""
    assert runs["reacher", "gem", "3", "5"]["diverged"] == ""
    assert runs["hopper", "gem", "0", "1"]["diverged"] == runs["hopper", "gem", "0", "5"]["diverged"] != ""
    assert set(NEW_KEYS) <= set(runs["reacher", "gem", "3", "1"]) and len(runs) == (15 + 6 + 4) * 2


def first_row(markdown, model):
    """The cells of the first table row of ``model`` in ``markdown``."""
    line = next(line for line in markdown.splitlines() if line.startswith(f"| {model} |"))
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def test_prediction_md_shows_diverged_runs_as_such_and_no_nan_or_inf(fake_offline):
    out, _ = fake_offline
    md = (out / "prediction.md").read_text()
    tables = "\n".join(line for line in md.splitlines() if line.startswith("|"))
    assert not re.search(r"\b(nan|inf|None)\b", tables, re.I), "a non-finite or missing number reached a table"
    sections = dict(re.findall(r"^## (\w+) [^\n]*\n(.*?)(?=^## )", md, re.S | re.M))
    model, seeds, h1, h5 = first_row(sections["reacher"].split("### mean_step_error")[1], "gem2")
    assert seeds == "5"  # the model's runs
    assert "diverged" not in h1 and h5.endswith("] (1 diverged)")  # h=1: every run; h=5: one left out
    assert first_row(sections["hopper"], "gem") == ["gem", "2", "all diverged", "all diverged"]
    assert "- reacher-gem2-s3: standardized_error 7e+04 >= the no-information level 1.41 at h=5" in md
    assert "- hopper-gem-s0: standardized_error inf at h=1; standardized_error inf at h=5" in md
    assert "### rotation_error" in sections["reacher"] and "### rotation_error" not in sections["invertedpendulum"]
    assert "### standardized_error" in sections["reacher"] and "P(mean_step_error < delta's)" in sections["reacher"]
    assert "Fewer than 5 seeds cannot carry a claim" in sections["invertedpendulum"]
    assert "Fewer than 5 seeds cannot carry a claim" in sections["reacher"]  # gem and gem2 have 4 seeds at h=5
    for name in ("relative_error.png", "ratio_to_delta.png", "absolute_error_reacher.png"):
        assert (out / name).stat().st_size > 10_000


def test_relative_error_csv_normalises_by_the_largest_model(fake_offline):
    out, _ = fake_offline
    rows = [r for r in csv_rows(out / "relative_error.csv") if r["metric"] == "mean_step_error"]
    reacher = {r["model"]: r for r in rows if r["env"] == "reacher"}
    top = max(float(r["iqm"]) for r in reacher.values())
    assert top == float(reacher["gem2"]["iqm"])  # gem2's errors are the largest
    for r in reacher.values():
        assert float(r["relative"]) == pytest.approx(float(r["iqm"]) / top, rel=1e-12)
        assert float(r["relative_ci_high"]) == pytest.approx(float(r["ci_high"]) / top, rel=1e-12)
    assert float(reacher["gem2"]["relative"]) == 1.0
    averaged = [np.mean([fake_values("gem", s, h)["mean_step_error"] for h in (1, 5)]) for s in range(4)]
    assert float(reacher["gem"]["iqm"]) == pytest.approx(metrics.aggregate_iqm(np.array(averaged)), rel=1e-12)
    hopper = {r["model"]: r for r in rows if r["env"] == "hopper"}
    assert hopper["gem"]["relative"] == "" and float(hopper["delta"]["relative"]) == 1.0


def test_old_evaluations_without_the_new_keys_are_summarised_too(tmp_path):
    old = ["mean_step_error", "final_step_error", "position_error", "velocity_error", "other_error"]
    for model in ("delta", "gem"):
        for seed in range(5):
            fake_eval(tmp_path, "reacher", model, seed, {str(h): fake_values(model, seed, h, old) for h in (1, 5)})
    rows = summarise_offline(tmp_path, ["reacher"], ["delta", "gem"], range(5), FAKE_REQUEST, reps=50)
    metrics_seen = list(dict.fromkeys(r["metric"] for r in rows))
    assert metrics_seen == ["mean_step_error", "final_step_error", "velocity_error", "other_error", "position_error"]
    assert all(r["n_seeds"] == 5 for r in rows)
    md = (tmp_path / "prediction.md").read_text()
    assert "### mean_step_error" in md and "### standardized_error" not in md and "Fewer than 5" not in md


@pytest.mark.parametrize("mode, extra", [("offline", []), ("online", ["--trials", 1])])
def test_five_seeds_by_default(mode, extra, monkeypatch, capsys, tmp_path):
    seen = []

    def fake_compare(env_names, models, seeds, *args, **kwargs):
        seen.append(seeds)
        tmp_path.joinpath("summary.md" if mode == "online" else "prediction.md").write_text("report")
        return {"failed": {}}

    monkeypatch.setattr(cli_module, f"compare_{mode}", fake_compare)
    args = [mode, "--envs", "reacher", "--models", "delta", *extra, "--out", tmp_path]
    code, printed, err = cli(capsys, *args)
    assert code == 0 and seen[-1] == [0, 1, 2, 3, 4] and err == "" and "report" in printed
    code, _, err = cli(capsys, *args, "--seeds", "0,1,2")
    assert code == 0 and seen[-1] == [0, 1, 2]


def test_fewer_than_five_seeds_give_one_warning_line():
    assert arguments.few_seeds_warning(5) is None and arguments.few_seeds_warning(12) is None
    assert arguments.few_seeds_warning(3) == (
        "pets.compare: warning: 3 seeds: fewer than 5 seeds cannot carry a claim "
        "(with n <= 3 the 95 % CI is the min-max of the seeds)"
    )
    assert arguments.few_seeds_warning(1).startswith("pets.compare: warning: 1 seed: fewer than 5")


# --------------------------------------------------------------------------- pool and usage errors
def test_process_pool_reports_a_failed_job_and_finishes_the_others():
    jobs = [
        ("good", arguments.split_list, ("a,b", "x")),
        ("bad", arguments.split_list, ("a,,b", "x")),
        ("also good", arguments.parse_seeds, ("3,1",)),
    ]
    results = runner.run_pool(jobs, 2, processes=True, progress=False, desc="test")
    assert results["good"] == (True, ["a", "b"]) and results["also good"] == (True, [3, 1])
    assert results["bad"][0] is False and "UsageError" in results["bad"][1] and "empty items" in results["bad"][1]


_SWEEP = """
import os, sys, time
from pathlib import Path

def job(pid_file):  # a job of the process pool: says its pid, then works for two minutes
    Path(pid_file).write_text(str(os.getpid()))
    time.sleep(120)

if __name__ == "__main__":
    from pets.experiments import runner
    import sweep

    kind, out = sys.argv[1], Path(sys.argv[2])
    child = "import os, sys, time; open(sys.argv[1], 'w').write(str(os.getpid())); time.sleep(120)"
    if kind == "threads":  # as the online runs: threads waiting on subprocesses
        jobs = [(f"j{i}", runner.run_logged, ([sys.executable, "-c", child, str(out / f"j{i}.pid")], out / f"j{i}.log"))
                for i in range(4)]
    else:  # as the offline runs: the jobs run in spawned worker processes
        jobs = [(f"j{i}", sweep.job, (str(out / f"j{i}.pid"),)) for i in range(4)]
    try:
        runner.run_pool(jobs, 2, processes=kind == "processes", progress=False, desc="sweep")
    except KeyboardInterrupt:
        print("interrupted", flush=True)
"""


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from Linux's /proc")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.parametrize("kind", ["threads", "processes"])
def test_a_stopped_sweep_starts_no_more_jobs_and_leaves_no_process_running(tmp_path, kind, sig):
    """SIGINT (Ctrl-C, ``kill -INT``) or SIGTERM to the sweep's process alone: the queued jobs never start and the
    running ones stop (an online run resumes its last trial, an offline job is redone), instead of the sweep going
    on without it (seen: offline workers computing for 10 minutes after their driver was killed)."""
    (tmp_path / "sweep.py").write_text(_SWEEP)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(runner.ROOT)])}
    proc = subprocess.Popen(
        [sys.executable, str(tmp_path / "sweep.py"), kind, str(tmp_path)],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=default_sigint,
    )
    try:
        deadline = time.monotonic() + 120
        while len([p for p in tmp_path.glob("j*.pid") if p.read_text()]) < 2:
            assert proc.poll() is None and time.monotonic() < deadline, "the first two jobs did not start"
            time.sleep(0.1)
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=180)  # seconds on a quiet machine; minutes were seen under load 9
    finally:
        proc.kill()
    assert proc.returncode == (0 if sig == signal.SIGINT else -sig)
    assert ("interrupted" in out) == (sig == signal.SIGINT)
    time.sleep(0.5)  # the running jobs' processes get SIGTERM or SIGKILL, which takes effect at once
    pids = {p.name: int(p.read_text()) for p in tmp_path.glob("j*.pid")}
    assert sorted(pids) == ["j0.pid", "j1.pid"]  # the queued jobs never started
    assert not [pid for pid in pids.values() if alive(pid)]


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["online", "--envs", "pong", "--models", "delta", "--trials", 1], "unknown env 'pong'"),
        (["online", "--envs", "reacher", "--models", "delta,transformer", "--trials", 1], "accepted: delta, gem"),
        (["online", "--envs", "reacher", "--models", "delta", "--seeds", "0,x", "--trials", 1], "--seeds"),
        (["online", "--envs", "reacher,", "--models", "delta", "--trials", 1], "without empty items"),
        # an item given twice would silently make a smaller study than the list reads
        (["online", "--envs", "reacher", "--models", "delta", "--seeds", "0,1,01", "--trials", 1], "names 1 twice"),
        (["online", "--envs", "reacher,Reacher-v5", "--models", "delta", "--trials", 1], "names 'reacher' twice"),
        (["offline", "--envs", "reacher", "--models", "delta,gem,delta"], "--models names 'delta' twice"),
        (["offline", "--envs", "reacher", "--models", "delta", "--data-seeds", "2,2"], "--data-seeds names 2 twice"),
        # data set D collects with seed 100 D + 1: past 2**32 - 1 its collection failed after the checks
        (["offline", "--envs", "reacher", "--models", "delta", "--data-seeds", "0,42949673"], "must be <= 42,949,672"),
        (["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "--planners", "cem,cem"], "'cem' twice"),
        (["online", "--envs", "reacher", "--models", "delta", "--trials", 0], "must be >= 1"),
        (
            ["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "planner.popsize=3"],
            "planner.population",
        ),
        (["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "seed=3"], "--seeds"),
        (
            ["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "trials=2"],
            "set by the command itself (--trials)",
        ),
        (["online", "--envs", "reacher", "--models", "delta", "--trials", 1, "--planners", "cem,ddp"], "accepted: cem"),
        (
            [
                "online",
                "--envs",
                "reacher",
                "--models",
                "delta",
                "--trials",
                1,
                "--planners",
                "cem",
                "planner.name=mppi",
            ],
            "--planners or planner.name=",
        ),
        (["offline", "--envs", "reacher", "--models", "delta", "--horizons", "1,a"], "comma-separated"),
        (["offline", "--envs", "reacher", "--models", "delta", "--openloop", "--planners", "cem,ddp"], "accepted: cem"),
        # planning options without the planning they set planned nothing and said nothing
        (["offline", "--envs", "reacher", "--models", "delta", "--planners", "mppi"], "--planners sets the planning"),
        (["offline", "--envs", "reacher", "--models", "delta", "--openloop", "--closedloop-steps", 9], "--closedloop,"),
        (["offline", "--envs", "reacher", "--models", "delta", "--closedloop", "--openloop-steps", 9], "--openloop,"),
        (
            ["offline", "--envs", "reacher", "--models", "delta", "--policy", "run:x"],
            "smooth-random[:BETA], sac[:STEPS] or existing",
        ),
        (["online", "--envs", "reacher", "--models", "delta"], "--trials"),
        (["sweep", "--envs", "reacher"], "invalid choice"),
    ],
)
def test_bad_input_exits_2_with_one_line(args, fragment, capsys, tmp_path):
    code, _, err = cli(capsys, *args, "--out", tmp_path / "never")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, err
    assert "error:" in lines[0] and fragment in lines[0]
    assert not (tmp_path / "never").exists()


def test_a_file_of_its_own_that_cannot_be_written_is_one_line_and_exit_3_the_runs_kept(tmp_path, capsys):
    """A summary or headline file pets.compare could not write (a full disk; here a directory in its way) ended the
    command with an OSError traceback (exit 1) after its runs had finished; now one line naming the file, exit 3,
    the runs kept, and the same command reruns to write it."""
    out, headline = tmp_path / "cmp", tmp_path / "headline"
    for blocked in (out / "summary.md", headline / "headline.md"):
        blocked.mkdir(parents=True)
    advice = (  # not "free space": a directory is in the way
        "it is a directory, not a file; what was finished is kept: move or delete that directory, then rerun the "
        "same command"
    )
    args = ["online", "--envs", "invertedpendulum", "--models", "delta", "--seeds", 0, "--trials", 1, "--out", out]
    args += ["--preset", "fast", "--quiet", *TINY]
    code, _, err = cli(capsys, *args)
    said = [line for line in err.splitlines() if "error" in line or "Traceback" in line]
    assert code == EXIT_FAILED, err
    assert said == [f"pets.compare: error: writing {out / 'summary.md'} failed (Is a directory): {advice}"]
    assert len(rundir.read_metrics(out / "runs" / "invertedpendulum-delta-s0" / "metrics.csv")) == 1
    (out / "summary.md").rmdir()
    assert cli(capsys, *args)[0] == 0 and (out / "summary.md").is_file()
    offline = ROOT / "docs" / "results" / "paper_ip_summary.csv"
    code, _, err = cli(capsys, "headline", "--offline", offline, "--online", out / "summary.csv", "--out", headline)
    said = [line for line in err.splitlines() if "error" in line or "Traceback" in line]
    assert code == EXIT_FAILED and said == [
        f"pets.compare: error: writing {headline / 'headline.md'} failed (Is a directory): {advice}"
    ]


def test_models_come_from_config_heads_at_run_time(monkeypatch):
    from pets import config

    monkeypatch.setattr(config, "HEADS", ("delta", "gem", "novel"))
    assert arguments.parse_models("novel,delta") == ["novel", "delta"]


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--planner", "ddp"], "unknown planner 'ddp'"),
        (["model.lr=0.1"], "must be planner keys"),
        (["planner.horizon=3"], "--steps"),
        (["planner.population=abc"], "planner.population"),
        (["--steps", "0"], "--steps must be >= 1"),
    ],
)
def test_openloop_bad_input_exits_2(args, fragment, offline, capsys):
    out, _ = offline
    with pytest.raises(SystemExit) as err:
        openloop.main(["--run", str(out / "runs" / "invertedpendulum-delta-s0"), *args])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert err.value.code == 2 and len(lines) == 1 and fragment in lines[0]


def test_arms_compare_a_model_with_its_own_overrides_in_one_command(tmp_path, capsys):
    """--arm LABEL=MODEL:key=value,...: its runs get the model plus its overrides, under LABEL in the tables."""
    single = "delta-x1=delta:model.ensemble_size=1,model.num_elites=1"
    args = ["offline", "--envs", "invertedpendulum", "--models", "delta", "--arm", single, "--seeds", "0,1"]
    args += ["--episodes", 3, "--test-episodes", 1, "--horizons", "1,2", "--starts", 10, "--preset", "fast"]
    code, out, _ = cli(capsys, *args, "--device", "cpu", "--quiet", "--out", tmp_path / "off", *TINY_OFFLINE)
    assert code == 0 and "| delta-x1 |" in out
    cfg = load_config(str(tmp_path / "off" / "runs" / "invertedpendulum-delta-x1-s1" / "config.yaml"))
    assert (cfg.head, cfg.model.ensemble_size, cfg.model.num_elites) == ("delta", 1, 1)
    assert (
        load_config(str(tmp_path / "off" / "runs" / "invertedpendulum-delta-s1" / "config.yaml")).model.num_elites == 2
    )
    rows = csv_rows(tmp_path / "off" / "summary.csv")
    assert {r["model"] for r in rows} == {"delta", "delta-x1"}
    assert all(r["ratio_to_delta"] for r in rows if r["model"] == "delta-x1" and r["metric"] == "mean_step_error")

    args = ["online", "--envs", "invertedpendulum", "--models", "gem", "--arm", "gem-h3=gem:planner.horizon=3"]
    code, out, _ = cli(
        capsys, *args, "--seeds", "0", "--trials", 1, "--preset", "fast", "--quiet", "--out", tmp_path / "on", *TINY
    )
    assert code == 0 and "| gem-h3 |" in out
    cfg = load_config(str(tmp_path / "on" / "runs" / "invertedpendulum-gem-h3-s0" / "config.yaml"))
    assert (cfg.head, cfg.planner.horizon) == ("gem", 3)


@pytest.mark.parametrize(
    "arm, fragment",
    [
        ("delta=gem", "not a model name"),
        ("x=transformer", "unknown model 'transformer' in --arm x"),
        ("x=gem:seed=3", "--arm x sets seed="),
        ("x=gem:model.lr", "--arm must be LABEL=MODEL[:key=value,key=value]"),
        ("x=gem:model.nope=1", "model.nope"),
    ],
)
def test_bad_arms_are_one_line_exit_2(arm, fragment, tmp_path, capsys):
    code, _, err = cli(
        capsys, "online", "--envs", "reacher", "--models", "delta", "--arm", arm, "--trials", 1, "--out", tmp_path / "x"
    )
    assert code == 2 and fragment in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "x").exists()


def test_online_until_threshold_stops_each_run_at_the_mark_and_counts_it_complete(tmp_path, capsys, monkeypatch):
    """--until-threshold: stop_reward = the env's threshold, a run ends after its first trial at or above it, is
    complete with fewer than --trials rows (summary, reuse), and resuming it adds nothing."""
    from pets.experiments.studies.online import THRESHOLDS

    monkeypatch.setitem(THRESHOLDS, "invertedpendulum", 3.0)  # every tiny episode lasts >= 3 steps: trial 0 stops
    args = ["online", "--envs", "invertedpendulum", "--models", "delta", "--seeds", "0,1", "--trials", 4, "--out",
            tmp_path, "--preset", "fast", "--quiet", "--until-threshold", *TINY]  # fmt: skip
    code, _, err = cli(capsys, *args)
    assert code == 0, err
    for seed in (0, 1):
        run = tmp_path / "runs" / f"invertedpendulum-delta-s{seed}"
        rows = csv_rows(run / "metrics.csv")
        assert len(rows) == 1 and float(rows[0]["episode_reward"]) >= 3.0
        assert load_config(str(run / "config.yaml")).stop_reward == 3.0
    summary = online_row(tmp_path, "invertedpendulum", "delta")
    assert (summary["n_seeds"], summary["n_reached"]) == ("2", "2")
    before = snapshot(tmp_path / "runs" / "invertedpendulum-delta-s0")
    code, _, err = cli(capsys, *args)
    assert code == 0 and "2 reused" in err and snapshot(tmp_path / "runs" / "invertedpendulum-delta-s0") == before
    code, _, err = cli(capsys, *[a if a != "invertedpendulum" else "hopper" for a in args])
    assert code == 2 and "--until-threshold: no threshold for hopper" in err
    code, _, err = cli(capsys, *[a for a in args if a != "--until-threshold"], "stop_reward=5")
    assert code == 2 and "stop_reward= is set by --until-threshold" in err


@pytest.mark.parametrize("mode", ["online", "offline"])
def test_a_second_sweep_into_the_same_out_is_refused_in_one_line_while_the_first_works(mode, tmp_path, capsys):
    """Two commands in one --out would fail each other's runs (each run directory is locked) and overwrite each
    other's summaries: while one holds OUT's lock, another exits 2 in one line and starts nothing."""
    from pets.runs.fileio import locked

    args = [mode, "--envs", "invertedpendulum", "--models", "delta", "--seeds", "0", "--out", tmp_path, "--quiet"]
    args += ["--trials", 1, *TINY] if mode == "online" else ["--episodes", 3, "--test-episodes", 1, *TINY_OFFLINE]
    with locked(tmp_path):  # the first sweep
        code, _, err = cli(capsys, *args)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{tmp_path} is in use" in err and "one sweep at a time in a directory" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == [".lock"]


def test_online_a_run_whose_training_diverges_counts_as_the_worst_outcome_and_is_not_rerun(tmp_path, capsys):
    """A run that stops because its model training diverged (run_pets exits 3) records why in its directory;
    the comparison counts it as diverged (the worst outcome in the exact test), not as a missing run, exits 0, and a
    rerun reuses it instead of training it into the same divergence again."""
    args = ["online", "--envs", "invertedpendulum", "--models", "delta", "--arm", "gem-lr=gem:model.lr=1e30",
            "--seeds", "0,1", "--trials", 2, "--out", tmp_path, "--preset", "fast", "--quiet", *TINY]  # fmt: skip
    code, _, err = cli(capsys, *args)
    assert code == 0, err
    for seed in (0, 1):
        why = (tmp_path / "runs" / f"invertedpendulum-gem-lr-s{seed}" / rundir.DIVERGED_FILE).read_text()
        assert "model training diverged" in why
    row = online_row(tmp_path, "invertedpendulum", "gem-lr")
    assert (row["n_seeds"], row["n_diverged"]) == ("0", "2")
    finals = [float(r["final_reward"]) for r in csv_rows(tmp_path / "summary_runs.csv") if r["model"] == "delta"]
    worst = [min(finals) - f for f in finals]  # each diverged run enters as the env's lowest final reward
    assert float(row["diff_p_signflip"]) == pytest.approx(sign_flip_p(np.array(worst)))
    md = (tmp_path / "summary.md").read_text()
    assert (
        "invertedpendulum-gem-lr-s0: stopped after 0 of 2 trials: training on the seed data before trial 0: model" in md
    )
    assert "Missing or incomplete" not in md
    code, _, err = cli(capsys, *args)
    assert code == 0 and "4 reused" in err, err
    # a divergence after the trials summarised does not count (a run extended past them, then diverged)
    delta = tmp_path / "runs" / "invertedpendulum-delta-s0"
    rundir.record_divergence(delta, "trial 5: model training diverged (a later extension)")
    code, _, err = cli(capsys, *args)
    assert code == 0 and online_row(tmp_path, "invertedpendulum", "delta")["n_diverged"] == "0", err
    rundir.record_divergence(delta, None)
    # a run made before the config key imports: the line says what to add to its config.yaml
    written = (delta / "config.yaml").read_text()
    (delta / "config.yaml").write_text("\n".join(x for x in written.splitlines() if not x.startswith("imports:")))
    code, _, err = cli(capsys, *args, "imports=[json]")
    assert code == 2 and "was made before the config key imports; add `imports: ['json']` to its config.yaml" in err


def test_online_at_an_env_step_budget_counts_runs_that_end_there_and_leaves_the_cut_episode_out(tmp_path, capsys):
    """--preset locomotion (its trials an upper bound, --trials not needed): a run that ends at its env-step budget
    is complete (summary, reuse); its last episode, cut by the budget, is in neither the final reward nor AUC."""
    from pets.experiments.rundirs import cut_by_budget

    args = ["online", "--envs", "invertedpendulum", "--models", "delta", "--seeds", "0", "--out", tmp_path,
            "--preset", "locomotion", "--quiet", *TINY, "max_env_steps=300", "train_every=100",
            "model.iterations=5", "model.compile=false"]  # fmt: skip
    code, out, err = cli(capsys, *args)
    assert code == 0, err
    run = tmp_path / "runs" / "invertedpendulum-delta-s0"
    assert load_config(str(run / "config.yaml")).trials == 100_000
    rows = csv_rows(run / "metrics.csv")
    last = rows[-1]
    assert int(last["env_steps"]) == 300 and last["terminated"] == "0" and int(last["episode_length"]) < 30
    assert cut_by_budget(rows, 300, 30) and not cut_by_budget(rows, 301, 30) and not cut_by_budget(rows, None, 30)
    assert not cut_by_budget([{**last, "episode_length": "30"}], 300, 30)  # ended at its step limit: complete
    rewards = [float(r["episode_reward"]) for r in rows[:-1]]
    (per_run,) = csv_rows(tmp_path / "summary_runs.csv")
    assert float(per_run["final_reward"]) == pytest.approx(np.mean(rewards[-3:]))
    assert float(per_run["auc"]) == pytest.approx(np.mean(rewards))
    assert online_row(tmp_path, "invertedpendulum", "delta")["n_seeds"] == "1"
    summary = (tmp_path / "summary.md").read_text()
    assert "(runs to their env-step budget, at most 100000 trials)" in summary and "Missing" not in summary
    code, _, err = cli(capsys, *args)
    assert code == 0 and "1 reused, 0 to resume, 0 to start" in err, err
    code, _, err = cli(capsys, *[a if a != "locomotion" else "fast" for a in args])
    assert code == 2 and "--trials is required (or trials in a --config file or a --preset that sets it)" in err


# --------------------------------------------------------------------------- headline across summaries
def test_headline_takes_each_comparison_from_the_summaries_at_the_longest_horizon(fake_offline, fake_online, tmp_path):
    off, _ = fake_offline
    on, _ = fake_online
    text = write_headline(
        [off / "summary.csv"], [on / "summary.csv"], tmp_path, horizon=50, relative=[off / "relative_error.csv"]
    )
    rows = csv_rows(tmp_path / "headline_offline.csv")
    assert {(r["env"], r["model"]) for r in rows} == {
        ("reacher", "gem"),
        ("reacher", "gem2"),
        ("invertedpendulum", "gem"),
        ("hopper", "gem"),
    }
    hopper = [r for r in rows if r["env"] == "hopper"]  # gem diverged in both seeds: counted, no ratio
    assert hopper and all(
        (r["n_diverged"], r["delta_n_diverged"], r["ratio_to_delta"]) == ("2", "0", "") for r in hopper
    )
    assert all(float(r["p_improvement"]) == 0 for r in hopper)
    for r in rows:
        assert r["horizon"] == "5"  # the longest below 50
        s = summary_row(off, r["env"], r["model"], 5, r["metric"])
        for col in ("p_improvement", "p_improvement_ci_low", "p_improvement_ci_high", "n_diverged"):
            assert float(r[col]) == float(s[col]), (r, col)
        assert r["p_value_exact"] == s["p_value_exact"] and r["ci_exact_note"] == s["ci_exact_note"]
        assert r["ratio_to_delta"] == s["ratio_to_delta"] or float(r["ratio_to_delta"]) == float(s["ratio_to_delta"])
        assert r["delta_n_diverged"] == summary_row(off, r["env"], "delta", 5, r["metric"])["n_diverged"]
    # invertedpendulum has no rotations: its rotation errors are 0, so there is nothing to compare
    assert {r["metric"] for r in rows if r["env"] == "invertedpendulum"} == {"standardized_error", "mean_step_error"}
    assert {r["horizon"] for r in csv_rows(write_dir(tmp_path, off, horizon=1) / "headline_offline.csv")} == {"1"}
    online = {(r["env"], r["model"]): r for r in csv_rows(tmp_path / "headline_online.csv")}
    assert set(online) == {("reacher", "gem"), ("reacher", "gem2"), ("hopper", "gem")}
    gem, delta = online_row(on, "reacher", "gem"), online_row(on, "reacher", "delta")
    assert float(online["reacher", "gem"]["final_iqm"]) == float(gem["final_iqm"])
    assert float(online["reacher", "gem"]["delta_final_iqm"]) == float(delta["final_iqm"])
    assert float(online["reacher", "gem"]["p_improvement"]) == float(gem["p_improvement"])
    assert float(online["reacher", "gem"]["p_fewer_steps"]) == float(gem["p_fewer_steps"])
    for col in ("diff_p_signflip", "diff_p_holm", "ci_exact_note"):
        assert online["reacher", "gem"][col] == gem[col] != "", col
    notes = [r for r in [*rows, *online.values()] if r["ci_exact_note"]]
    assert notes and "Where the bootstrap CI and the exact test disagree" in text
    assert "| reacher | gem |" in text and "nan" not in text.lower().replace("n/a", "")
    for figure in ("headline_ratio.png", "headline_relative.png", "headline_fig2_ratio.png"):
        assert (tmp_path / figure).stat().st_size > 0
    relative = csv_rows(off / "relative_error.csv")  # reacher's delta tracks the state at h = 1 only
    assert {r["horizons"] for r in relative} == {"1 5"}
    for r in relative:
        r["horizons"] = "1" if r["env"] == "reacher" else r["horizons"]
    write_csv(tmp_path / "relative_error.csv", relative, list(relative[0]))
    text = write_headline([off / "summary.csv"], [], tmp_path / "t", relative=[tmp_path / "relative_error.csv"])
    by_env = {r["env"]: r["horizon"] for r in csv_rows(tmp_path / "t" / "headline_offline.csv")}
    assert by_env == {"reacher": "1", "invertedpendulum": "5", "hopper": "5"} and "among its tracking horizons" in text


def write_dir(tmp_path, off, horizon):
    out = tmp_path / f"h{horizon}"
    write_headline([off / "summary.csv"], [], out, horizon=horizon)
    return out


def test_headline_rejects_what_is_not_a_summary_in_one_line(fake_offline, tmp_path, capsys):
    off, _ = fake_offline
    code, _, err = cli(capsys, "headline", "--offline", tmp_path / "missing.csv", "--out", tmp_path / "h")
    assert code == 2 and "no such file" in err and "Traceback" not in err
    code, _, err = cli(capsys, "headline", "--online", off / "summary.csv", "--out", tmp_path / "h")
    assert code == 2 and "an offline summary given as --online" in err
    code, _, err = cli(capsys, "headline", "--closedloop", off / "summary.csv", "--out", tmp_path / "h")
    assert code == 2 and "not a pets.compare closedloop.csv" in err and "Traceback" not in err
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    code, _, err = cli(capsys, "headline", "--offline", tmp_path / "other.csv", "--out", tmp_path / "h")
    assert code == 2 and "not a pets.compare summary.csv" in err
    args = ("--offline", off / "summary.csv", "--relative", off / "summary.csv", "--out", tmp_path / "h")
    code, _, err = cli(capsys, "headline", *args)
    assert code == 2 and "not a pets.compare relative_error.csv" in err
    args = ("--offline", off / "summary.csv", "--out", tmp_path / "h", "--figures", tmp_path / "figs")
    code, out, _ = cli(capsys, "headline", *args)
    assert code == 0 and out.startswith("# Headline") and (tmp_path / "h" / "headline.md").read_text() in out
    assert "](../figs/headline_ratio.png)" in out and (tmp_path / "figs" / "headline_ratio.png").is_file()
    code, _, err = cli(capsys, "headline", "--primary", off / "summary.csv", "--out", tmp_path / "h")
    assert code == 2 and "not a primary.csv" in err and "Traceback" not in err
    (tmp_path / "afile").write_text("x")  # each of these was a traceback, or an empty headline with exit 0
    with open(off / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r["horizon"] = "x1" if r["model"] == "gem" else r["horizon"]  # was int()'s ValueError
    write_csv(tmp_path / "bad.csv", rows, list(rows[0]))
    for args, fragment in (
        (
            ("--offline", off / "summary.csv", "--out", tmp_path / "afile"),
            "--out " + str(tmp_path / "afile") + " is a file",
        ),
        (("--offline", off / "summary.csv", "--out", tmp_path / "h", "--figures", tmp_path / "afile"), "is a file"),
        # below a file: was an OSError traceback once the headline was made
        (("--offline", off / "summary.csv", "--out", tmp_path / "afile" / "h"), f"{tmp_path / 'afile'} is a file"),
        (
            ("--offline", off / "summary.csv", "--out", tmp_path / "h", "--figures", tmp_path / "afile" / "f"),
            f"--figures {tmp_path / 'afile' / 'f'} cannot be made: {tmp_path / 'afile'} is a file; give a directory",
        ),
        (("--offline", off / "summary.csv", "--out", tmp_path / "h", "--horizon", "0"), "--horizon must be >= 1"),
        (("--offline", off / "summary.csv", "--out", tmp_path / "h", "--model", "nope"), "--model nope is in none of"),
        (("--offline", tmp_path / "bad.csv", "--out", tmp_path / "h"), "a summary holds a value that is not"),
    ):
        code, _, err = cli(capsys, "headline", *args)
        assert code == 2 and len(err.strip().splitlines()) == 1 and fragment in err, (args, err)


def test_headline_gives_the_primary_endpoint_as_the_files_do(fake_offline, tmp_path):
    """Issue 37: --primary puts the pre-registered endpoint first, every number as its primary.csv has it."""
    off, _ = fake_offline
    text = write_headline([off / "summary.csv"], [], tmp_path, primary=[off / "primary.csv"])
    assert text.index("## Primary endpoint") < text.index("## Offline prediction error")
    compared = [r for r in csv_rows(off / "primary.csv") if r["model"] != "delta" and r["p_value_holm"]]
    assert compared
    for r in compared:
        line = next(x for x in text.splitlines() if x.startswith(f"| {r['env']} | {r['model']} |"))
        assert f"| {float(r['p_value_holm']):.3g} |" in line and r["verdict"] in line
        assert f"| {r['tracking_horizons']} |" in line


def test_headline_keeps_each_primary_files_family_apart(fake_offline, tmp_path):
    """Issue 32: two studies' primary.csv files (e.g. the gem-se study beside issue 37's) give two tables, each
    headed by its file, every row in its own file's table, not one table with two Holm families mixed."""
    off, _ = fake_offline
    other = tmp_path / "other_primary.csv"
    rows = csv_rows(off / "primary.csv")
    with other.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows({**r, "p_value_holm": "0.5" if r["p_value_holm"] else ""} for r in rows)
    text = write_headline([], [], tmp_path / "h", primary=[off / "primary.csv", other])
    first, second = (text.index(f"## Primary endpoint (pre-registered, docs/experiments.md): `{p}`")
                     for p in (off / "primary.csv", other))  # fmt: skip
    assert first < second
    for r in (r for r in rows if r["p_value_holm"]):
        lines = [x for x in text.splitlines() if x.startswith(f"| {r['env']} | {r['model']} |")]
        assert len(lines) == 2
        assert f"| {float(r['p_value_holm']):.3g} |" in lines[0] and "| 0.5 |" in lines[1]


def test_table_numbers_are_readable():
    """Four significant digits, large counts written out (env steps), non-finite values spelt out."""
    assert fmt(0.59374) == "0.5937"
    assert fmt(1135.155) == "1135"
    assert fmt(13333.33) == "13333"
    assert fmt(-16666.7) == "-16667"
    assert fmt(7e12) == "7e+12"
    assert fmt(float("nan")) == "nan"
    assert fmt_interval(13333.3, 10666.7, float("inf")) == "n/a"


# --------------------------------------------------------------------------- precisions resolved per machine
def _as_if_started_on_another_cpu_kind(run_dir):
    """Rewrite a run's recorded precisions to the other concrete value, as ``auto`` resolves on a machine of
    another CPU kind (bf16 where native, fp32 elsewhere) in a study spread over a mixed cluster, and its
    ``model.compile`` the other way too (the fast preset's ``auto`` follows the precision: on with bf16, for a run
    long enough to compile)."""
    cfg = load_config(str(run_dir / "config.yaml"))
    other = "fp32" if cfg.planner.precision == "bf16" else "bf16"
    cfg.planner.precision = cfg.model.precision = other
    cfg.model.compile = not cfg.model.compile
    rundir.write_config(run_dir, cfg)
    return other


def test_online_rerun_accepts_runs_whose_auto_precision_resolved_elsewhere_and_says_so(online, tmp_path, capsys):
    """planner.precision and model.precision left at auto: a run started on a machine of another CPU kind holds
    the other concrete value. A rerun reuses it (it used to refuse the directory as "made with another config",
    so such a study could not be resumed or summarised) and summary.md names the precisions per run; an explicit
    precision is still compared."""
    import shutil

    copy = tmp_path / "study"
    shutil.copytree(online[0], copy)
    other = _as_if_started_on_another_cpu_kind(copy / "runs" / "invertedpendulum-gem-s1")
    common = ["--envs", "invertedpendulum", "--models", "delta,gem", "--seeds", "0,1", "--trials", 2]
    common += ["--out", copy, "--workers", 1, "--preset", "fast", "--quiet", *TINY]
    code, _, err = cli(capsys, "online", *common)
    assert code == 0 and "4 reused" in err
    md = (copy / "summary.md").read_text()
    assert "## The runs used different precisions" in md
    assert f"- {other} / {other}, compiled training: 1 runs (invertedpendulum-gem-s1)" in md  # the others eager
    mine = "bf16" if other == "fp32" else "fp32"
    code, _, err = cli(capsys, "online", *common, f"planner.precision={mine}", f"model.precision={mine}")
    assert code == 2 and "invertedpendulum-gem-s1 was made with another config" in err
    assert f"planner.precision: '{other}' != '{mine}'" in err
    flipped = load_config(str(copy / "runs" / "invertedpendulum-gem-s1" / "config.yaml")).model.compile
    code, _, err = cli(capsys, "online", *common, f"model.compile={not flipped}")
    assert code == 2 and f"model.compile: {flipped} != {not flipped}" in err  # set on the line: compared
    assert "different precisions" not in (online[0] / "summary.md").read_text()  # one machine: no note


def test_offline_rerun_accepts_runs_whose_auto_precision_resolved_elsewhere_and_says_so(offline, tmp_path, capsys):
    import shutil

    copy = tmp_path / "study"
    shutil.copytree(offline[0], copy)
    other = _as_if_started_on_another_cpu_kind(copy / "runs" / "invertedpendulum-delta-s0")
    code, _, err = cli(capsys, *OFFLINE_ARGS, "--out", copy)
    assert code == 0, err
    md = (copy / "prediction.md").read_text()
    assert f"- {other} / {other}, compiled training: 1 runs (invertedpendulum-delta-s0)" in md


def _offline_copy_summarised(offline, tmp_path, data_seeds=(0,)):
    """A copy of the offline fixture's directory, summarised again at its own settings (other tests re-summarise the
    fixture with other models or horizons), with ``data_seeds``; the compare_offline result."""
    import shutil

    out = tmp_path / "offline"
    shutil.copytree(offline[0], out)
    kwargs = dict(episodes=8, test_episodes=4, horizons=[1, 3, 5], starts=20, preset="fast", device="cpu")
    result = compare_offline(
        ["invertedpendulum"], ["delta", "gem"], [0, 1], out, overrides=TINY_OFFLINE, progress=False,
        data_seeds=list(data_seeds), **kwargs,
    )  # fmt: skip
    assert result["failed"] == {}
    return out, result


def test_offline_primary_endpoint_recomputed_from_the_runs_and_data(offline, tmp_path):
    """Issue 37: the no-information level from the data sets (numpy here), the tracking horizons, the clipped
    endpoint per run, the paired ratio and its exact p-value (scipy's permutation test)."""
    from pets.learning.evaluation import MIN_STD

    out, _ = _offline_copy_summarised(offline, tmp_path)
    (train, test) = (dict(np.load(out / "data" / f"invertedpendulum-{p}.npz")) for p in ("train", "test"))

    def real(a):
        return a["obs"][np.arange(a["obs"].shape[1])[None, :] <= a["lengths"][:, None]].astype(np.float64)

    sigma = real(train).std(axis=0)
    sigma = np.where(sigma < MIN_STD, 1.0, sigma)
    pick = np.random.default_rng(0).integers(0, len(real(train)), size=len(real(test)))
    level = np.sqrt((((real(test) - real(train)[pick]) / sigma) ** 2).mean(axis=1)).mean()  # IP: no angle wraps
    rows = {r["model"]: r for r in csv_rows(out / "primary.csv")}
    assert float(rows["gem"]["level"]) == pytest.approx(level, rel=1e-9) and rows["gem"]["level_source"].startswith(
        "data ("
    )
    err = {
        (m, s): json.loads((out / "runs" / f"invertedpendulum-{m}-s{s}" / "eval.json").read_text())["horizons"]
        for m in ("delta", "gem")
        for s in (0, 1)
    }
    median = {h: np.median([err["delta", s][h]["standardized_error"] for s in (0, 1)]) for h in ("1", "3", "5")}
    tracking = [h for h in ("1", "3", "5") if median[h] < level]  # the tiny models track all 5 steps
    assert rows["gem"]["tracking_horizons"] == " ".join(tracking) == "1 3 5"
    endpoint = {k: np.mean([min(v[h]["standardized_error"], level) for h in tracking]) for k, v in err.items()}
    ratios = np.array([endpoint["gem", s] / endpoint["delta", s] for s in (0, 1)])
    assert float(rows["gem"]["ratio_to_delta"]) == pytest.approx(ratios.mean(), rel=1e-12)
    exact = scipy.stats.permutation_test(
        (np.log(ratios),), np.mean, permutation_type="samples", n_resamples=np.inf
    ).pvalue
    assert float(rows["gem"]["p_value_exact"]) == pytest.approx(exact) == float(rows["gem"]["p_value_holm"])
    assert rows["gem"]["verdict"] == "no difference shown" and rows["delta"]["ratio_to_delta"] == ""
    assert "## Primary endpoint (pre-registered" in (out / "prediction.md").read_text()
    summary = [r for r in csv_rows(out / "summary.csv") if r["model"] == "gem" and r["metric"] == "mean_step_error"]
    assert all(float(r["p_value_exact"]) in (0.5, 1.0) for r in summary)  # 2 pairs: 2 / 4 or 4 / 4


def printed_configs(monkeypatch, capsys, *args):
    """``--print-config`` through main: (exit code, stdout, stderr, every run's resolved config as a dict)."""
    from omegaconf import OmegaConf

    seen = {}
    real = cli_module.print_shared_config

    def spy(parsed, configs):
        seen.update({name: OmegaConf.to_container(cfg) for name, cfg in configs.items()})
        real(parsed, configs)

    monkeypatch.setattr(cli_module, "print_shared_config", spy)
    return (*cli(capsys, *args, "--print-config"), seen)


@pytest.mark.parametrize("mode", ["online", "offline"])
def test_compare_print_config_round_trips_through_config(tmp_path, capsys, monkeypatch, mode):
    """Issue 35: pets.compare --print-config prints the settings every run shares (nothing is run or written),
    valid as --config: fed back with the same options it gives the same text and the same config for every run;
    key=value on the line wins over the file."""
    monkeypatch.chdir(tmp_path)
    line = ["--envs", "reacher,ant", "--models", "gem,delta", "--seeds", "0,1", "--preset", "fast"]
    line += ["--trials", "3"] if mode == "online" else []
    code, printed, _, configs = printed_configs(monkeypatch, capsys, mode, *line, "planner.horizon=9")
    assert code == 0 and len(configs) == 8 and not list(tmp_path.iterdir())
    assert "horizon: 9" in printed and "per run (not here" in printed and "\nenv:" not in printed
    assert {c["planner"]["horizon"] for c in configs.values()} == {9}
    file = tmp_path / "shared.yaml"
    file.write_text(printed)
    code, again, _, configs_again = printed_configs(monkeypatch, capsys, mode, *line, "--config", file)
    assert code == 0 and again == printed and configs_again == configs
    code, won, _, configs_won = printed_configs(monkeypatch, capsys, mode, *line, "--config", file, "planner.horizon=4")
    assert code == 0 and "horizon: 4" in won and {c["planner"]["horizon"] for c in configs_won.values()} == {4}
    # one env and one model: the file holds env and head (and online trials), so it stands for those options too
    one = ["--envs", "reacher", "--models", "gem", *(["--trials", "2"] if mode == "online" else [])]
    code, single, _, configs_one = printed_configs(monkeypatch, capsys, mode, *one, "--seeds", "3")
    assert code == 0 and "env: reacher" in single and "head: gem" in single
    file.write_text(single)
    code, back, _, configs_back = printed_configs(monkeypatch, capsys, mode, "--config", file, "--seeds", "3")
    assert code == 0 and back == single and configs_back == configs_one


def test_compare_config_file_reaches_the_runs_and_bad_files_get_one_line(tmp_path, capsys, monkeypatch):
    """A --config file's keys reach every run's config.yaml, key=value after it wins; a run_pets.py config (with
    a seed) gets a note that --seeds decides; a typo gets "did you mean"; a missing option or bad device exits 2."""
    monkeypatch.chdir(tmp_path)
    keys = dict(item.split("=") for item in TINY)
    file = tmp_path / "tiny.yaml"
    file.write_text("".join(f"{k}: {v}\n" for k, v in keys.items()) + "env: reacher\nhead: gem\ntrials: 1\nseed: 7\n")
    out = tmp_path / "out"
    code, _, err = cli(capsys, "online", "--config", file, "--seeds", "0", "--out", out, "--quiet", "planner.horizon=3")
    assert code == 0, err
    assert "seed: 7 not used" in err
    cfg = load_config(str(out / "runs" / "reacher-gem-s0" / rundir.CONFIG_FILE))
    assert (cfg.env, cfg.head, cfg.trials, cfg.seed) == ("reacher", "gem", 1, 0)
    assert cfg.planner.horizon == 3 and cfg.planner.population == 16 and cfg.episode_length == 30
    for content, extra, fragment in (
        (
            "env: reacher\nhead: gem\ntrials: 1\nplanner:\n  horizn: 3\n",
            [],
            "unknown config key 'planner.horizn'; did you mean planner.horizon?",
        ),
        ("- a list\n", [], "expected a mapping of config keys, got a list"),
        ("head: gem\n", [], "--envs is required (or env in a --config file)"),
        ("env: reacher\nhead: gem\n", [], "--trials is required (or trials in a --config file or a --preset that"),
        ("env: reacher\nhead: gem\ntrials: 1\ndevice: tpu\n", [], "device must be cpu, cuda or auto, got 'tpu'"),
        ("env: reacher\nhead: gem\ntrials: 1\n", ["--print-config", "x"], "expected key=value, got 'x'"),
    ):
        (tmp_path / "bad.yaml").write_text(content)
        code, _, err = cli(capsys, "online", "--config", tmp_path / "bad.yaml", "--out", tmp_path / "o2", *extra)
        lines = [x for x in err.splitlines() if x.strip()]
        assert code == 2 and len(lines) == 1 and fragment in lines[0], err
    assert not (tmp_path / "o2").exists()


def _script(name: str):
    """docs/scripts/NAME.py imported as a module."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "docs" / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_offline_data_seeds_pair_by_data_set_and_seed(offline, tmp_path):
    """Issue 37: --data-seeds 0,1 reuses data set 0 and its runs, collects data set 1 with its own seeds, runs every
    model and seed on it, and pairs the primary endpoint by (data seed, seed)."""
    out, result = _offline_copy_summarised(offline, tmp_path, data_seeds=(0, 1))
    assert result["data"]["invertedpendulum-train.npz"] == "reused"
    assert (
        result["data"]["invertedpendulum-d1-train.npz"]
        == result["data"]["invertedpendulum-d1-test.npz"]
        == ("collected")
    )
    assert {n for n, todo in result["todo"].items() if "train" in todo} == {
        f"invertedpendulum-{m}-d1-s{s}" for m in ("delta", "gem") for s in (0, 1)
    }  # data set 0's runs were trained before (other tests may have changed their horizons: evaluated again)
    train, test = (np.load(out / "data" / f"invertedpendulum-d1-{p}.npz") for p in ("train", "test"))
    assert (int(train["seed"]), int(test["seed"])) == (100, 101)
    runs = csv_rows(out / "prediction_runs.csv")
    assert {(r["data_seed"], r["seed"]) for r in runs} == {(d, s) for d in "01" for s in "01"}
    err = {
        (m, d, s): json.loads((out / "runs" / name / "eval.json").read_text())
        for m in ("delta", "gem")
        for d in (0, 1)
        for s in (0, 1)
        if (name := f"invertedpendulum-{m}{'-d1' if d else ''}-s{s}")
    }
    assert err["gem", 1, 0]["data"].endswith("invertedpendulum-d1-test.npz")
    row = {r["model"]: r for r in csv_rows(out / "primary.csv")}["gem"]
    assert (row["n_pairs"], row["n_data_sets"]) == ("4", "2")
    level, hs = float(row["level"]), row["tracking_horizons"].split()

    def endpoint(e):
        return np.mean([min(e["horizons"][h]["standardized_error"], level) for h in hs])

    ratios = [endpoint(err["gem", d, s]) / endpoint(err["delta", d, s]) for d in (0, 1) for s in (0, 1)]
    assert float(row["ratio_to_delta"]) == pytest.approx(scipy.stats.trim_mean(ratios, 0.25), rel=1e-12)
    exact = scipy.stats.permutation_test((np.log(ratios),), np.mean, permutation_type="samples", n_resamples=np.inf)
    assert float(row["p_value_exact"]) == pytest.approx(exact.pvalue)
    assert float(row["ratio_ci_low"]) <= float(row["ratio_to_delta"]) <= float(row["ratio_ci_high"])
    snapshot = _script("partial_offline_runs")  # its --data-seeds summary is the study's own, read-only on the runs
    args = [str(out), str(tmp_path / "runs.csv"), "--summary", str(tmp_path / "snap"), "--envs", "invertedpendulum"]
    assert snapshot.main([*args, "--models", "delta,gem", "--seeds", "0,1", "--data-seeds", "0,1"]) == 0
    for name in ("summary.csv", "primary.csv"):
        assert csv_rows(tmp_path / "snap" / name) == csv_rows(out / name), name


def test_partial_offline_snapshot_of_a_finished_study_is_its_own_summary(offline, tmp_path):
    """docs/scripts/partial_offline_runs.py: one row per run and horizon from eval.json, and with --summary the
    summary of the finished runs, written beside the study (nothing under it); for a finished study that is the
    study's own summary.csv and primary.csv, value for value; --levels: its data set's level, primary.csv's."""
    partial = _script("partial_offline_runs")
    import shutil

    study = tmp_path / "study"  # other tests reuse the module's study: summarise a copy, made current first
    shutil.copytree(offline[0], study)
    kwargs = dict(episodes=8, test_episodes=4, horizons=[1, 3, 5], starts=20, preset="fast", device="cpu")
    compare_offline(["invertedpendulum"], ["delta", "gem"], [0, 1], study, overrides=TINY_OFFLINE, progress=False,
                    **kwargs)  # fmt: skip
    before = sorted(p.name for p in study.iterdir())
    args = [str(study), str(tmp_path / "runs.csv"), "--summary", str(tmp_path / "snap"), "--envs", "invertedpendulum"]
    levels = tmp_path / "levels.csv"
    assert partial.main([*args, "--models", "delta,gem", "--seeds", "0,1", "--levels", str(levels)]) == 0
    rows = csv_rows(tmp_path / "runs.csv")
    assert {(r["model"], r["seed"]) for r in rows} == {(m, s) for m in ("delta", "gem") for s in ("0", "1")}
    assert sorted(p.name for p in study.iterdir()) == before
    for name in ("summary.csv", "primary.csv"):
        assert csv_rows(tmp_path / "snap" / name) == csv_rows(study / name), name
    (level,) = csv_rows(levels)  # the data set's no-information level: the one the study's primary endpoint used
    assert (level["env"], level["data_seed"]) == ("invertedpendulum", "0")
    assert float(level["level"]) == pytest.approx(float(csv_rows(study / "primary.csv")[0]["level"]), rel=1e-12)
    # the rows it holds are merged: a data set not under the study (made on a machine since replaced) keeps its
    # rows; one under it has the rows of its runs there alone (a run of it not there is a withdrawn one)
    gone = {**rows[0], "run": "invertedpendulum-delta-d7-s0", "data": "invertedpendulum-d7-test.npz"}
    withdrawn = {**rows[0], "run": "invertedpendulum-delta-s9", "seed": "9"}
    write_csv(tmp_path / "runs.csv", [withdrawn, *rows, gone], list(rows[0]))
    assert partial.main([str(study), str(tmp_path / "runs.csv")]) == 0
    assert csv_rows(tmp_path / "runs.csv") == sorted([*rows, gone], key=lambda r: (r["run"], int(r["horizon"])))


def test_trajectory_figures_of_a_study_add_the_horizon_where_delta_stops_tracking(offline, tmp_path, capsys):
    """docs/scripts/trajectory_figures.py (issue 38): one figure per env from the study's seed-0 runs; a column at
    the first evaluated horizon outside delta's tracking horizons (primary.csv) when it is earlier than the last."""
    import shutil

    figures = _script("trajectory_figures")
    study = tmp_path / "study"
    shutil.copytree(offline[0], study)
    rows = csv_rows(study / "primary.csv")
    for r in rows:
        r["tracking_horizons"] = "1"  # delta tracks at h = 1 only: the figure gains the next evaluated horizon
    write_csv(study / "primary.csv", rows, list(rows[0]))
    args = [str(study), "--envs", "invertedpendulum", "--steps", "0,4", "--start", "0", "--figures", str(tmp_path)]
    assert figures.main(args) == 0
    line = capsys.readouterr().out
    evaluated = sorted({int(r["horizon"]) for r in csv_rows(study / "summary.csv")})  # e.g. 1, 3, 5
    columns = sorted({0, 4, *([evaluated[1]] if evaluated[1] < 4 else [])})
    assert "trajectories_invertedpendulum.png: invertedpendulum" in line
    assert line.rstrip().endswith("t = " + ", ".join(map(str, columns))) and evaluated[1] < 4
    assert (tmp_path / "trajectories_invertedpendulum.png").stat().st_size > 1000
    with pytest.raises(SystemExit, match="no trained run"):
        figures.main([*args, "--models", "delta,gem-se"])


def test_offline_closedloop_plans_with_the_frozen_models_and_pairs_them(offline, tmp_path):
    """Issue 38: --closedloop drives MPC with every trained model (no training: the checkpoints are untouched),
    writes closedloop_PLANNER.json per run and closedloop.csv with the paired difference to delta and its exact p."""
    import shutil

    out = tmp_path / "offline"
    shutil.copytree(offline[0], out)
    ckpt = {d.name: (d / "checkpoint.pt").read_bytes() for d in (out / "runs").iterdir()}
    kwargs = dict(episodes=8, test_episodes=4, horizons=[1, 3, 5], starts=20, preset="fast", device="cpu")
    result = compare_offline(
        ["invertedpendulum"], ["delta", "gem"], [0, 1], out, overrides=TINY_OFFLINE, progress=False,
        closedloop=True, closedloop_steps=10, planners=["cem"], openloop_episodes=2, **kwargs,
    )  # fmt: skip
    assert result["failed"] == {} and all("closedloop_cem" in todo for todo in result["todo"].values())
    assert {d.name: (d / "checkpoint.pt").read_bytes() for d in (out / "runs").iterdir()} == ckpt
    res = {
        (m, s): json.loads((out / "runs" / f"invertedpendulum-{m}-s{s}" / "closedloop_cem.json").read_text())
        for m in ("delta", "gem")
        for s in (0, 1)
    }
    spec = envs.get("invertedpendulum")
    sim = spec.make()
    r = res["gem", 1]
    assert r["mode"] == "closed" and r["steps"] == 10 and r["episodes"] == 2
    for i in range(2):  # the recorded rewards are the simulator's for the executed actions
        sim.reset(seed=r["reset_seeds"][i])
        for t in range(r["lengths"][i]):
            assert sim.step(np.array(r["executed_actions"][i][t]))[1] == pytest.approx(r["rewards"][i][t])
    assert r["reset_seeds"] == res["delta", 1]["reset_seeds"]  # paired: the same episodes for every model
    row = {x["model"]: x for x in csv_rows(out / "closedloop.csv")}["gem"]
    d = [res["gem", s]["total"]["mean"] - res["delta", s]["total"]["mean"] for s in (0, 1)]
    assert float(row["diff_to_delta"]) == pytest.approx(np.mean(d), rel=1e-12) and row["n_pairs"] == "2"
    exact = scipy.stats.permutation_test((np.array(d),), np.mean, permutation_type="samples", n_resamples=np.inf)
    assert float(row["p_value_exact"]) == pytest.approx(exact.pvalue)
    assert (out / "closedloop.md").is_file() and (out / "closedloop_invertedpendulum.png").stat().st_size > 1000
    # the headline's planning column takes these numbers as the summary wrote them
    text = write_headline([], [], tmp_path / "h", closedloop=[out / "closedloop.csv"])
    (head,) = csv_rows(tmp_path / "h" / "headline_planning.csv")
    delta = {x["model"]: x for x in csv_rows(out / "closedloop.csv")}["delta"]
    assert (head["env"], head["loop"], head["planner"], head["model"]) == ("invertedpendulum", "closed", "cem", "gem")
    for key in ("total_mean", "diff_to_delta", "diff_ci_low", "diff_ci_high", "p_value_exact", "n_pairs"):
        assert float(head[key]) == float(row[key]), key
    assert float(head["delta_total_mean"]) == float(delta["total_mean"])
    assert "## Planning with a pre-trained model" in text
    assert "| invertedpendulum | closed | cem | 10 | gem | 2 |" in text
    assert float(head["p_value_holm"]) == float(row["p_value_exact"])  # a family of one
    # Holm over the envs given, for gem in closed loop: a second env's file (the same rows under another env name)
    other = [{**x, "env": "reacher"} for x in csv_rows(out / "closedloop.csv")]
    other = [{**x, "p_value_exact": "0.04"} if x["model"] == "gem" else x for x in other]
    write_csv(tmp_path / "other.csv", other, list(other[0]))
    write_headline([], [], tmp_path / "h2", closedloop=[out / "closedloop.csv", tmp_path / "other.csv"])
    adjusted = {r["env"]: float(r["p_value_holm"]) for r in csv_rows(tmp_path / "h2" / "headline_planning.csv")}
    expected = holm([float(row["p_value_exact"]), 0.04])
    assert [adjusted["invertedpendulum"], adjusted["reacher"]] == pytest.approx(expected)
    # a CI that excludes 0 beside an exact p that does not carry it: the note, in the CSV and under the table
    odd = [{**x, "diff_ci_low": "1", "diff_ci_high": "2", "p_value_exact": "0.5"} if x["model"] == "gem" else x
           for x in other]  # fmt: skip
    write_csv(tmp_path / "odd.csv", odd, list(odd[0]))
    text = write_headline([], [], tmp_path / "h3", closedloop=[tmp_path / "odd.csv"])
    (note,) = [r["ci_exact_note"] for r in csv_rows(tmp_path / "h3" / "headline_planning.csv")]
    assert note == ci_exact_note(1.0, 2.0, 0.0, 0.5) != ""
    assert f"disagree (the exact p carries a claim): reacher / gem / closed cem: {note}." in text
    with pytest.raises(HeadlineError, match="not a pets.compare openloop.csv"):
        write_headline([], [], tmp_path / "h", openloop=[out / "summary.csv"])
    # --planner-overrides: recorded in the request, so the runs plan anew with them (and only then)
    again = dict(closedloop=True, closedloop_steps=10, planners=["cem"], openloop_episodes=2, **kwargs)
    over = {"planner.population": "24", "planner.iterations": "1"}
    result = compare_offline(["invertedpendulum"], ["delta", "gem"], [0, 1], out, overrides=TINY_OFFLINE,
                             progress=False, planner_overrides=over, **again)  # fmt: skip
    assert all(todo == ["closedloop_cem"] for todo in result["todo"].values()) and len(result["todo"]) == 4
    planned = json.loads((out / "runs" / "invertedpendulum-gem-s1" / "closedloop_cem.json").read_text())
    assert (planned["planner_config"]["population"], planned["planner_config"]["iterations"]) == (24, 1)
    assert planned["request"]["overrides"] == over and r["planner_config"]["population"] != 24
    assert "planner.population=24" in (out / "closedloop.md").read_text()
    result = compare_offline(["invertedpendulum"], ["delta", "gem"], [0, 1], out, overrides=TINY_OFFLINE,
                             progress=False, planner_overrides=over, **again)  # fmt: skip
    assert result["todo"] == {}
    bad = dict(overrides=TINY_OFFLINE, progress=False, planner_overrides={"planner.horizon": "5"}, openloop=True)
    with pytest.raises(UsageError, match="--planner-overrides: .*planner.horizon"):
        compare_offline(["invertedpendulum"], ["delta"], [0], out, planners=["cem"], **bad, **kwargs)
    # checked against every run's config, not the first one's: here a replanning period only one run's horizon allows
    configs = {f"ip-h{h}": make_config("invertedpendulum", "delta", "fast", {"planner.horizon": h}) for h in (10, 4)}
    with pytest.raises(UsageError, match=r"planner.replan_every \(6\) must be <= planner.horizon \(4\) \(run ip-h4\)"):
        offline_mod._check_planner_overrides(configs, ["cem"], {"planner.replan_every": "6"}, False, True)
    with pytest.raises(UsageError, match="planner.KEY=VALUE"):
        arguments.parse_planner_overrides("population=5")
    parsed = arguments.parse_planner_overrides("planner.population=5,planner.feedback.features=[0,2],planner.alpha=0.2")
    assert parsed == {"planner.population": "5", "planner.feedback.features": "[0,2]", "planner.alpha": "0.2"}
    label, head, arm = arguments.parse_arm("fb=gem:planner.feedback.features=[0,2],planner.alpha=0.2")  # the same split
    assert (label, head, arm) == ("fb", "gem", {"planner.feedback.features": "[0,2]", "planner.alpha": "0.2"})
