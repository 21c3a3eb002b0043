"""The online locomotion study (pets.experiments.studies.locomotion; docs/studies/online_locomotion.md): one row per
run directory, the paired summary from the committed rows, checked against scipy's exact permutation test."""

from __future__ import annotations

import csv
import io
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats

from pets.experiments.report import write_rounded_csv
from pets.experiments.studies import locomotion as study
from tests import warm

FIELDS = ["trial", "env_steps", "episode_reward", "episode_length", "terminated", "cpu_time_s", "plan_cpu_s"]


def make_run(root: Path, model: str, seed: int, rewards: list[float], budget: int = 100_000) -> Path:
    """A run directory of HalfCheetah-shaped trials (1,000 steps each after 1,000 seed steps), cut at ``budget``."""
    run = root / f"halfcheetah-{model}-s{seed}"
    run.mkdir(parents=True)
    cfg = {"env": "halfcheetah", "head": model, "seed": seed, "max_env_steps": 100_000, "episode_length": None}
    (run / "config.yaml").write_text(yaml.safe_dump(cfg))
    with (run / "metrics.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        for i, r in enumerate(rewards):
            steps = 1000 * (i + 2)
            if steps > budget:
                break
            writer.writerow({"trial": i, "env_steps": steps, "episode_reward": r, "episode_length": 1000,
                             "terminated": 0, "cpu_time_s": 36.0 * (i + 1), "plan_cpu_s": 30.0})  # fmt: skip
    return run


def ramp(final: float) -> list[float]:
    """99 trials rising linearly to ``final`` (the last trial ends at the 100k budget)."""
    return [final * (i + 1) / 99 for i in range(99)]


def test_a_run_row_has_the_endpoint_the_auc_and_the_steps_to_the_threshold(tmp_path):
    rewards = ramp(3000.0)
    row = study.run_row(make_run(tmp_path, "delta", 0, rewards))
    assert row["status"] == "complete" and row["env_steps"] == 100_000
    assert row["endpoint"] == pytest.approx(np.mean(rewards[-5:]))
    # the window at n env steps holds the trials ending at n - 4000 ... n (trial i ends at 1000 * (i + 2))
    window = [np.mean(rewards[n // 1000 - 6 : n // 1000 - 1]) for n in range(10_000, 100_001, 1000)]
    assert row["auc"] == pytest.approx(np.mean(window))
    first = next(i for i in range(4, 99) if np.mean(rewards[i - 4 : i + 1]) >= 2800)
    assert row["steps_to_threshold"] == 1000 * (first + 2)
    assert row["cpu_hours"] == pytest.approx(36.0 * 99 / 3600, abs=1e-4)
    curve = study.curve_rows(tmp_path / "halfcheetah-delta-s0")
    assert [c["env_steps"] for c in curve] == list(range(10_000, 100_001, 1000))
    assert [c["reward"] for c in curve] == pytest.approx(window)
    partial = study.run_row(make_run(tmp_path, "gem", 0, rewards, budget=40_000))
    assert partial["status"] == "partial" and math.isnan(partial["endpoint"]) and math.isnan(partial["auc"])
    crashed = study.run_row(make_run(tmp_path, "gem-se", 0, rewards, budget=40_000), crashed=True)
    assert crashed["status"] == "crashed" and crashed["endpoint"] == 0.0 and crashed["auc"] == 0.0


def write_runs(path: Path, finals: dict[str, list[float]], partial: dict[str, int] | None = None) -> list[dict]:
    rows = []
    for model, values in finals.items():
        for seed, value in enumerate(values):
            row = dict.fromkeys(study.RUN_COLUMNS, "") | {"env": "halfcheetah", "model": model, "seed": seed}
            rows.append(row | {"env_steps": 100_000, "endpoint": value, "auc": value / 2, "cpu_hours": 1.5,
                               "status": "complete"})  # fmt: skip
    for model, seed in (partial or {}).items():
        rows.append(dict.fromkeys(study.RUN_COLUMNS, "") | {"env": "halfcheetah", "model": model, "seed": seed,
                                                             "env_steps": 40_000, "status": "partial"})  # fmt: skip
    write_rounded_csv(path, rows, study.RUN_COLUMNS)
    with path.open() as f:
        return list(csv.DictReader(f))


def test_the_summary_pairs_each_arm_with_delta_by_seed_against_scipys_exact_test(tmp_path):
    delta = [3000.0, 4400.0, 1300.0, 2500.0, 3600.0, 2000.0]
    gem = [3100.0, 4300.0, 1500.0, 2700.0, 3900.0, 1950.0]
    se = [2000.0, 4000.0, 1000.0, 2600.0, 3000.0, 1900.0]
    rows = write_runs(tmp_path / "runs.csv", {"delta": delta, "gem": gem, "gem-se": se}, {"delta-groupfeat": 0})
    summary = {r["model"]: r for r in study.summary_from_runs(rows, reps=200)}
    assert set(summary) == {"delta", "gem", "gem-se"}  # the partial run is not counted
    assert summary["delta"]["n_seeds"] == 6 and summary["delta"]["diff_to_delta"] is None
    p = {}
    for model, values in (("gem", gem), ("gem-se", se)):
        d = np.array(values) - np.array(delta)
        exact = stats.permutation_test((d,), np.mean, permutation_type="samples", n_resamples=np.inf).pvalue
        assert summary[model]["diff_p_signflip"] == pytest.approx(exact)
        assert summary[model]["n_pairs"] == 6
        assert summary[model]["diff_ci_low"] <= summary[model]["diff_to_delta"] <= summary[model]["diff_ci_high"]
        p[model] = exact
    low, high = sorted(p.values())  # Holm over the two tests
    adjusted = {m: (min(1, 2 * v) if v == low else min(1, max(2 * low, v))) for m, v in p.items()}
    for model in p:
        assert summary[model]["diff_p_holm"] == pytest.approx(adjusted[model])
    (versus,) = [r for r in study.versus_rows(rows, reps=200) if r["model"] == "gem-se"]
    d = np.array(se) - np.array(gem)
    assert versus["versus"] == "gem" and versus["n_higher"] == int((d > 0).sum())
    exact = stats.permutation_test((d,), np.mean, permutation_type="samples", n_resamples=np.inf).pvalue
    assert versus["p_signflip"] == pytest.approx(exact)


def test_a_crashed_run_enters_the_paired_test_as_zero(tmp_path):
    rows = write_runs(tmp_path / "runs.csv", {"delta": [3000.0] * 5, "gem": [3100.0] * 4 + [0.0]})
    rows[-1]["status"] = "crashed"
    (_, gem) = study.summary_from_runs(rows, reps=100)
    d = np.array([100.0] * 4 + [-3000.0])
    exact = stats.permutation_test((d,), np.mean, permutation_type="samples", n_resamples=np.inf).pvalue
    assert gem["n_seeds"] == 5 and gem["diff_p_signflip"] == pytest.approx(exact)


def test_a_crashed_run_is_below_every_run_where_returns_are_negative(tmp_path):
    """HalfCheetah's returns can be negative: a crashed run then enters as the env's lowest value, not 0, so it
    loses its pairing (here delta's seed 4 ends at -50, and gem's crashed seed 4 counts as -80, gem's seed 3)."""
    rows = write_runs(tmp_path / "runs.csv", {"delta": [300.0, 200.0, 100.0, 50.0, -50.0],
                                              "gem": [310.0, 210.0, 110.0, -80.0, 0.0]})  # fmt: skip
    rows[-1]["status"] = "crashed"
    (_, gem) = study.summary_from_runs(rows, reps=100)
    d = np.array([10.0, 10.0, 10.0, -130.0, -30.0])
    exact = stats.permutation_test((d,), np.mean, permutation_type="samples", n_resamples=np.inf).pvalue
    assert gem["n_seeds"] == 5 and gem["diff_p_signflip"] == pytest.approx(exact)
    assert gem["endpoint_iqm"] == pytest.approx(stats.trim_mean([310.0, 210.0, 110.0, -80.0, -80.0], 0.25))
    assert gem["auc_iqm"] == pytest.approx(stats.trim_mean([155.0, 105.0, 55.0, -40.0, -40.0], 0.25))


def test_the_report_makes_the_summary_and_both_blocks_from_the_runs_file(tmp_path, monkeypatch):
    from pets.experiments import published

    results = tmp_path / "docs" / "results"
    results.mkdir(parents=True)
    write_runs(results / study.RUNS, {"delta": [3000.0, 2000.0], "gem": [3500.0, 2100.0]}, {"gem-se": 0})
    runs = [make_run(tmp_path / m, m, s, ramp(3000.0)) for m in ("delta", "gem") for s in (0, 1)]
    curves = [c for run in runs for c in study.curve_rows(run)]
    write_rounded_csv(results / study.CURVES, curves, study.CURVE_COLUMNS)
    (tmp_path / "docs" / "figures").mkdir()
    monkeypatch.chdir(tmp_path)
    (product,) = [p for p in published.PRODUCTS if p.name == "online locomotion summary"]
    product.make()
    assert (tmp_path / study.FIGURE).read_bytes().startswith(b"\x89PNG")
    runs = study.runs_table(tmp_path).splitlines()
    assert runs[0] == "| env | arm | seed | env steps | 25k | 50k | 100k (endpoint) | CPU-hours | status |"
    assert runs[-1] == "| halfcheetah | gem-se | 0 | 40000 |  |  |  |  | partial |" and len(runs) == 7
    table = study.summary_table(tmp_path)
    assert "| halfcheetah | gem | 2 | 2800 [2100, 3500] |" in table and "| 300 [100, 500] | 2 | 0.5 |" in table
    assert "| gem | delta-groupfeat |" not in table  # no delta-groupfeat runs: no secondary row


def test_the_command_writes_the_runs_file_and_refuses_what_is_not_a_run(tmp_path):
    run = make_run(tmp_path, "delta", 0, ramp(3000.0))
    out = tmp_path / "runs.csv"
    cmd = [sys.executable, "-m", "pets.experiments.studies.locomotion"]
    proc = warm.run([*cmd, str(run), "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    (row,) = list(csv.DictReader(out.open()))
    assert row["model"] == "delta" and row["status"] == "complete" and list(row) == study.RUN_COLUMNS
    proc = warm.run([*cmd, str(tmp_path / "nope"), "--out", str(out)], capture_output=True, text=True,
                    timeout=120)  # fmt: skip
    assert proc.returncode == 2 and "no config.yaml" in proc.stderr and len(proc.stderr.splitlines()) == 1
    proc = warm.run([*cmd, str(run), "--out", str(out), "--crashed", str(tmp_path / "other")],
                    capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2 and "--crashed names runs not given" in proc.stderr


def test_identical_rows_stand_for_delta_groupfeat_on_a_planar_env_and_only_where_it_was_not_run(tmp_path):
    """On HalfCheetah (planar) a delta-groupfeat seed with no run takes gem's complete row, marked not run (no
    CPU-hours) and counted by the summary; a seed it ran keeps its own row, and must agree with gem's; on Ant (the
    torso on SO(3)) nothing is made up."""
    gem = {s: study.run_row(make_run(tmp_path / "gem", "gem", s, ramp(2000.0 + 500 * s))) for s in range(3)}
    own = study.run_row(make_run(tmp_path / "feat", "delta-groupfeat", 0, ramp(2000.0)))
    made = study.identical_rows([*gem.values(), own])
    assert [(r["model"], r["seed"]) for r in made] == [("delta-groupfeat", 1), ("delta-groupfeat", 2)]
    for r in made:
        assert r["status"] == study.IDENTICAL_STATUS and math.isnan(r["cpu_hours"])
        assert {k: r[k] for k in study.RUN_COLUMNS if k not in ("model", "cpu_hours", "status")} == pytest.approx(
            {k: gem[r["seed"]][k] for k in study.RUN_COLUMNS if k not in ("model", "cpu_hours", "status")}, nan_ok=True
        )
    assert study.planar("halfcheetah") and not study.planar("ant")
    assert study.identical_rows([{**g, "env": "ant"} for g in gem.values()]) == []
    differing = study.run_row(make_run(tmp_path / "other", "delta-groupfeat", 0, ramp(2100.0)))
    with pytest.raises(ValueError, match="halfcheetah seed 0: delta-groupfeat and gem differ in endpoint"):
        study.identical_rows([*gem.values(), differing])
    path = tmp_path / "runs.csv"
    write_rounded_csv(path, [*gem.values(), own, *made], study.RUN_COLUMNS)
    with path.open() as f:
        summary = {r["model"]: r for r in study.summary_from_runs(list(csv.DictReader(f)))}
    assert summary["delta-groupfeat"]["n_seeds"] == 3 and summary["gem"]["n_seeds"] == 3
    assert summary["delta-groupfeat"]["endpoint_iqm"] == pytest.approx(summary["gem"]["endpoint_iqm"])
    assert summary["delta-groupfeat"]["cpu_hours_mean"] == pytest.approx(own["cpu_hours"])  # the run it made


def test_the_command_adds_identical_rows_when_asked(tmp_path):
    runs = [make_run(tmp_path, "gem", s, ramp(2500.0)) for s in (0, 1)]
    out = tmp_path / "runs.csv"
    cmd = [sys.executable, "-m", "pets.experiments.studies.locomotion", *map(str, runs), "--out", str(out)]
    assert warm.run(cmd, capture_output=True, text=True, timeout=120).returncode == 0
    assert {r["model"] for r in csv.DictReader(out.open())} == {"gem"}
    assert warm.run([*cmd, "--identical"], capture_output=True, text=True, timeout=120).returncode == 0
    rows = list(csv.DictReader(out.open()))
    assert [(r["model"], r["seed"], r["status"]) for r in rows if r["model"] != "gem"] == [
        ("delta-groupfeat", "0", study.IDENTICAL_STATUS),
        ("delta-groupfeat", "1", study.IDENTICAL_STATUS),
    ]


def test_the_command_keeps_committed_rows_of_runs_not_given_and_replaces_those_given(tmp_path):
    """A run directory lost with a replaced machine must not lose its committed row: the runs and curves files
    keep it, in its place; a run given again replaces its rows once it reaches as far (while it is behind, as a
    run started again from the start, the committed rows stay); ``--replace`` writes only the runs given."""
    old = [make_run(tmp_path / "old", "delta", s, ramp(3000.0)) for s in (0, 1)]
    out, curves = tmp_path / "runs.csv", tmp_path / "curves.csv"
    files = ["--out", str(out), "--curves", str(curves)]
    assert study.main([*map(str, old), *files]) == 0
    committed = out.read_text(), curves.read_text()
    partial = make_run(tmp_path / "new", "delta", 1, ramp(2000.0), budget=50_000)
    assert study.main([str(partial), *files]) == 0
    assert (out.read_text(), curves.read_text()) == committed
    again = make_run(tmp_path / "again", "delta", 1, ramp(2000.0))
    assert study.main([str(again), *files]) == 0
    rows = list(csv.DictReader(out.open()))
    assert [(r["seed"], r["status"]) for r in rows] == [("0", "complete"), ("1", "complete")]
    assert rows[0] == next(csv.DictReader(io.StringIO(committed[0])))  # kept as committed, cell for cell
    assert float(rows[1]["endpoint"]) == pytest.approx(np.mean(ramp(2000.0)[-5:]), rel=1e-5)
    assert study.main([str(partial), *files, "--replace"]) == 0
    assert [(r["seed"], r["status"]) for r in csv.DictReader(out.open())] == [("1", "partial")]
    steps = {(r["seed"], r["env_steps"]) for r in csv.DictReader(curves.open())}
    assert ("1", "50000") in steps and ("1", "100000") not in steps and ("0", "100000") not in steps


def test_the_figure_draws_delta_groupfeat_only_where_it_is_not_gems_curve(tmp_path, monkeypatch):
    """On HalfCheetah (planar) delta-groupfeat's curve is gem's and is not drawn again; on Ant it is drawn."""
    runs, points = [], []
    for env in ("halfcheetah", "ant"):
        for model in ("delta", "gem", "delta-groupfeat"):
            runs.append({"env": env, "model": model, "seed": 0, "status": "complete"})
            points += [{"env": env, "model": model, "seed": 0, "env_steps": n, "reward": 1.0} for n in (1000, 2000)]
    write_rounded_csv(tmp_path / study.RUNS, runs, ["env", "model", "seed", "status"])
    write_rounded_csv(tmp_path / study.CURVES, points, study.CURVE_COLUMNS)
    drawn = {}
    monkeypatch.setattr(study.curves, "plot_curves", lambda path, arms, **kw: drawn.update(arms))
    study.plot_curves(tmp_path, tmp_path / "figure.png")
    assert sorted(drawn["halfcheetah"]) == ["delta", "gem"]
    assert sorted(drawn["ant"]) == ["delta", "delta-groupfeat", "gem"]


def test_the_answer_takes_the_study_for_an_env_once_every_preregistered_pair_is_in(tmp_path):
    """The answer table's online cell of HalfCheetah is the fast-preset study's until every arm of this study has
    its 10 pairs, then this study's paired endpoint for gem (scipy's exact p), with its legend."""
    import shutil

    from pets.experiments.answer import LOCOMOTION_LEGEND, answer_table
    from pets.experiments.published import RESULTS

    results = tmp_path / RESULTS
    shutil.copytree(Path(__file__).resolve().parents[1] / RESULTS, results)
    (tmp_path / "docs" / "figures").mkdir()
    delta = [3000.0, 4400.0, 1300.0, 2500.0, 3600.0, 2000.0, 3300.0, 2900.0, 4100.0, 1800.0]
    gem = [3100.0, 4300.0, 1500.0, 2700.0, 3900.0, 1950.0, 3500.0, 3000.0, 4400.0, 2100.0]

    def halfcheetah_cell(gem_seeds: int, se_seeds: int) -> str:
        arms = {"delta": delta, "gem": gem[:gem_seeds], "delta-groupfeat": gem, "gem-se": delta[:se_seeds]}
        write_runs(results / study.RUNS, arms)
        study.write_summary(results)
        (row,) = [r for r in answer_table(tmp_path).splitlines() if r.startswith("| halfcheetah |")]
        return row.split(" | ")[-1]

    for gem_seeds, se_seeds in ((9, 10), (10, 9)):
        assert halfcheetah_cell(gem_seeds, se_seeds).endswith("(online_halfcheetah_fast_5seeds) |")
    assert LOCOMOTION_LEGEND not in answer_table(tmp_path)
    cell = halfcheetah_cell(10, 10)
    d = np.array(gem) - np.array(delta)
    exact = stats.permutation_test((d,), np.mean, permutation_type="samples", n_resamples=np.inf).pvalue
    assert cell.endswith("(online_locomotion) |") and ", 10 pairs, p " in cell, cell
    assert float(cell.split(", p ")[1].split(",")[0]) == pytest.approx(exact, rel=1e-2)
    assert LOCOMOTION_LEGEND in answer_table(tmp_path)


def test_the_papers_claim_is_worded_by_the_registered_rule_per_env(tmp_path):
    """Reproduced only where gem ends higher than delta at family-wise 0.05 with every arm's 10 pairs in; not
    reproduced where the pairs are in and it does not; not shown where the gate did not pass; not yet before."""
    from pets.experiments.report import read_csv_rows

    delta = [3000.0, 4400.0, 1300.0, 2500.0, 3600.0, 2000.0, 3300.0, 2900.0, 4100.0, 1800.0]
    gates = [{"env": "halfcheetah", "agent": "delta", "verdict": "passed"},
             {"env": "ant", "agent": "delta", "verdict": "not passed"}]  # fmt: skip

    def claim(gem: list[float], se: list[float]) -> dict[str, str]:
        rows = write_runs(tmp_path / "runs.csv", {"delta": delta, "gem": gem, "delta-groupfeat": gem, "gem-se": se})
        write_rounded_csv(tmp_path / "s.csv", study.summary_from_runs(rows, reps=100), study.SUMMARY_COLUMNS)
        lines = study.claim_lines(read_csv_rows(tmp_path / "s.csv"), gates)
        assert lines[0].startswith("The paper's claim, \"GEM+PETS consistently achieves higher rewards")
        return {line.split(":")[0][2:]: line for line in lines[2:]}

    higher, lower = [d + 200 for d in delta], [d - 200 for d in delta]
    # every pair higher: exact p 2/1024 per test, Holm over the 3 tests 0.00586
    win = claim(higher, lower)
    assert win["halfcheetah"] == (
        "- halfcheetah: **reproduced** (gem's endpoint against delta's: higher, Holm p 0.00586; delta-groupfeat: "
        "higher; gem-se: lower) (a planar body: gem is GEM's inputs alone, nothing composes)"
    )
    assert win["ant"].startswith("- ant: **not shown** (the gate: not passed;")
    assert win["hopper"].startswith("- hopper: **not shown** (the gate: not run;")
    gates.append({"env": "hopper", "agent": "delta", "verdict": "partial"})
    partial = "- hopper: not yet (the gate: partial; the study runs there once it passes)"
    assert claim(higher, lower)["hopper"] == partial
    gates.pop()
    assert claim(lower, higher)["halfcheetah"].startswith("- halfcheetah: **not reproduced** (gem's endpoint against "
                                                          "delta's: lower, Holm p 0.00586;")  # fmt: skip
    mixed = [d + (200 if i % 2 else -200) for i, d in enumerate(delta)]
    assert (
        "**not reproduced** (gem's endpoint against delta's: no difference shown, Holm p 1;"
        in claim(mixed, mixed)["halfcheetah"]
    )
    assert claim(higher[:9], higher)["halfcheetah"] == (
        "- halfcheetah: not yet (pairs of 10 per arm: delta-groupfeat 9, gem 9, gem-se 10; no verdict is read before)"
    )


def test_the_figure_draws_every_arm_over_the_seeds_all_arms_have_complete(tmp_path, monkeypatch):
    """While the study runs, an arm with a seed another arm lacks (complete) is drawn without it: the lines compare
    the same seeds (here seeds 0-1; gem's seed 2 and delta's partial seed 2 are left out)."""
    runs, points = [], []
    for model, seeds in (("delta", (0, 1)), ("gem", (0, 1, 2)), ("gem-se", (0, 1, 2))):
        for seed in seeds:
            runs.append({"env": "halfcheetah", "model": model, "seed": seed, "status": "complete"})
            points += [{"env": "halfcheetah", "model": model, "seed": seed, "env_steps": 1000, "reward": 1.0}]
    runs.append({"env": "halfcheetah", "model": "delta", "seed": 2, "status": "partial"})
    write_rounded_csv(tmp_path / study.RUNS, runs, ["env", "model", "seed", "status"])
    write_rounded_csv(tmp_path / study.CURVES, points, study.CURVE_COLUMNS)
    drawn = {}
    monkeypatch.setattr(study.curves, "plot_curves", lambda path, arms, **kw: drawn.update(arms))
    study.plot_curves(tmp_path, tmp_path / "figure.png")
    assert {arm: sorted(members) for arm, members in drawn["halfcheetah"].items()} == {
        "delta": ["0", "1"],
        "gem": ["0", "1"],
        "gem-se": ["0", "1"],
    }
