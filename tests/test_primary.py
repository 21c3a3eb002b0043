"""The offline primary endpoint (pets.experiments.studies.primary, issue 37): level, tracking horizons, tests."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.stats

import envs
from pets.experiments.statistics import holm
from pets.experiments.studies.primary import (
    DEFAULT_LEVEL,
    no_information_level,
    past_level_rows,
    primary_markdown,
    primary_rows,
    tracking_horizons,
)
from tests import warm

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs/results"


def _offline_primary(*args: object) -> subprocess.CompletedProcess:
    """``docs/scripts/offline_primary.py`` with ``args``, run from the project root."""
    command = [sys.executable, str(ROOT / "docs/scripts/offline_primary.py"), *map(str, args)]
    return warm.run(command, capture_output=True, text=True, cwd=ROOT)


HORIZONS = (1, 5, 10, 25)


def _rows(env: str, model: str, errors: dict[int, list[float]]) -> list[dict]:
    """Per-run rows as prediction_runs.csv has them: {seed: [error per horizon of HORIZONS]}."""
    return [
        {"env": env, "model": model, "seed": s, "horizon": h, "standardized_error": e}
        for s, errs in errors.items()
        for h, e in zip(HORIZONS, errs)
    ]


def test_no_information_level_of_gaussian_data_is_sqrt2():
    """Independent draws of the same distribution: z = (x - y) / sigma ~ N(0, 2) per entry, so the RMS over the
    entries is sqrt(2) up to the RMS's small-sample bias (here d = 17 entries: E sqrt(chi2_d / d) * sqrt(2))."""
    layout = envs.get("halfcheetah").layout
    rng = np.random.default_rng(1)

    def data(n):  # std 0.1: hinge differences never reach pi, so no wrap changes an entry
        return {"obs": rng.normal(0.0, 0.1, (n, 51, layout.obs_dim)), "lengths": np.full(n, 50)}

    d = len(layout.predicted_indices)
    expected = math.sqrt(2.0 / d) * math.sqrt(2.0) * math.exp(math.lgamma((d + 1) / 2) - math.lgamma(d / 2))
    assert no_information_level(data(40), data(20), layout) == pytest.approx(expected, rel=0.01)
    assert expected == pytest.approx(DEFAULT_LEVEL, rel=0.02)


def test_tracking_horizons_stop_at_the_first_median_past_the_level():
    base = {
        0: {1: 0.1, 5: 0.5, 10: 2.0, 25: 0.3},
        1: {1: 0.2, 5: 0.6, 10: 1.0, 25: 0.2},
        2: {1: 0.1, 5: 9.0, 10: 3.0, 25: 1.0},
    }
    assert tracking_horizons(base, 1.5) == [1, 5]  # the median at 10 is 2.0; 25 comes after it and is not used
    assert tracking_horizons(base, 0.05) == []
    base[1][1], base[2][1] = math.nan, 0.12  # a diverged run counts as +inf: the median at h=1 is 0.12, not 0.11
    assert tracking_horizons(base, 0.115) == []


def test_primary_ratio_exact_p_and_holm_across_envs():
    delta = {s: [0.05 * (s + 1), 0.1 * (s + 1), 0.15 * (s + 1), 0.2 * (s + 1)] for s in range(5)}  # below sqrt(2)
    gem = {s: [0.8 * e for e in errs] for s, errs in delta.items()}  # 20 % lower at every horizon, every seed
    worse = {s: [1.1 * e for e in errs] for s, errs in delta.items()}
    rows = primary_rows(
        _rows("a", "delta", delta) + _rows("a", "gem", gem) + _rows("b", "delta", delta) + _rows("b", "gem", worse)
    )
    by = {(r["env"], r["model"]): r for r in rows}
    assert [r["model"] for r in rows] == ["delta", "gem", "delta", "gem"]  # the baseline first
    a, b = by["a", "gem"], by["b", "gem"]
    assert a["ratio_to_delta"] == pytest.approx(0.8) and b["ratio_to_delta"] == pytest.approx(1.1)
    assert a["tracking_horizons"] == "1 5 10 25" and a["n_pairs"] == 5 and a["level"] == DEFAULT_LEVEL
    assert a["p_value_exact"] == b["p_value_exact"] == 2 / 32  # every seed one way: the smallest 5-pair p
    assert [a["p_value_holm"], b["p_value_holm"]] == holm([2 / 32, 2 / 32]) == [0.125, 0.125]
    assert a["verdict"] == b["verdict"] == "no difference shown"  # 5 pairs can never be significant
    # the bootstrap CI of 5 identical ratios is [0.8, 0.8] (excludes 1), the exact p 0.0625: the summary says so
    assert a["ci_exact_note"] == "the bootstrap CI excludes 1, the exact p is 0.0625: not significant at 0.05"
    assert "Where the bootstrap CI and the exact test disagree" in "\n".join(primary_markdown(rows))
    assert "a / gem: the bootstrap CI excludes 1" in "\n".join(primary_markdown(rows))
    # gem seed i (0.8 (i + 1)) beats delta seeds j > 0.8 (i + 1) - 1; gem s4 ties delta s3 (4.0): half
    assert a["p_improvement"] == pytest.approx(15.5 / 25)


def test_primary_clips_at_the_level_and_counts_a_diverged_run_as_the_level():
    delta = {s: [0.2, 0.4, 0.9, 1.2] for s in range(6)}
    gem = {s: [0.1, 0.2, 0.5, 0.6] for s in range(6)}
    gem[5] = [0.1, math.nan, math.inf, 1e9]  # diverged from h=5: scores the level there, never dropped
    rows = primary_rows(_rows("e", "delta", delta) + _rows("e", "gem", gem), {"e": (1.0, "given")})
    (base, row) = rows
    assert base["tracking_horizons"] == row["tracking_horizons"] == "1 5 10"  # delta's median reaches 1.2 at h=25
    clipped_delta = np.mean([0.2, 0.4, 0.9])
    ratios = [np.mean([0.1, 0.2, 0.5]) / clipped_delta] * 5 + [np.mean([0.1, 1.0, 1.0]) / clipped_delta]
    assert row["n_pairs"] == 6 and row["n_past_level"] == 1 and base["n_past_level"] == 0
    exact = scipy.stats.permutation_test((np.log(ratios),), np.mean, permutation_type="samples", n_resamples=np.inf)
    assert row["p_value_exact"] == pytest.approx(exact.pvalue)
    assert row["level_source"] == "given"


def test_no_test_without_a_tracking_horizon_and_past_level_counts():
    delta = {s: [5.0, 6.0, 7.0, 8.0] for s in range(5)}
    rows = primary_rows(_rows("e", "delta", delta) + _rows("e", "gem", delta))
    assert all(r["verdict"].startswith("no test: the baseline's median is past the level") for r in rows)
    assert all("p_value_exact" not in r for r in rows)
    past = {(r["model"], r["horizon"]): r for r in past_level_rows(_rows("e", "gem", {0: [1.0, 2.0, math.nan, 1.0]}))}
    assert [past["gem", h]["n_past_level"] for h in HORIZONS] == [0, 1, 1, 0]
    assert past["gem", 10]["median_error"] == math.inf


def test_versus_compares_two_arms_on_the_primary_endpoint_at_the_baselines_horizons():
    """gem-se against gem: per seed the ratio of their primary endpoints (delta's tracking horizons, the level's
    clipping), its IQM = scipy's 25 %-trimmed mean, the exact p = scipy's permutation test, no Holm."""
    from pets.experiments.studies.primary import versus_rows

    delta = {s: [0.2, 0.4, 0.9, 1.2] for s in range(6)}  # tracking horizons 1, 5, 10 at level 1.0
    gem = {s: [0.1 * (1 + s / 10), 0.2, 0.5, 5.0] for s in range(6)}
    se = {s: [0.1, 0.2 * (1 - s / 20), 2.0, 0.1] for s in range(6)}  # clipped at h=10; h=25 not read
    rows = _rows("e", "delta", delta) + _rows("e", "gem", gem) + _rows("e", "gem-se", se)
    [row] = versus_rows(rows, [("gem-se", "gem"), ("gem", "absent")], {"e": (1.0, "given")})
    ratios = np.array(
        [np.mean([0.1, 0.2 * (1 - s / 20), 1.0]) / np.mean([0.1 * (1 + s / 10), 0.2, 0.5]) for s in range(6)]
    )
    assert (row["model"], row["versus"], row["tracking_horizons"], row["n_pairs"]) == ("gem-se", "gem", "1 5 10", 6)
    assert row["ratio"] == pytest.approx(scipy.stats.trim_mean(ratios, 0.25))
    exact = scipy.stats.permutation_test((np.log(ratios),), np.mean, permutation_type="samples", n_resamples=np.inf)
    assert row["p_value_exact"] == pytest.approx(exact.pvalue) and row["n_lower"] == int((ratios < 1).sum())
    assert row["ratio_ci_low"] <= row["ratio"] <= row["ratio_ci_high"]


def test_offline_primary_script_writes_the_versus_table(tmp_path):
    delta = {s: [0.2, 0.4, 0.9, 1.2] for s in range(5)}
    gem = {s: [0.1, 0.2, 0.5, 0.6] for s in range(5)}
    rows = _rows("e", "delta", delta) + _rows("e", "gem", gem) + _rows("e", "gem-se", delta)
    runs = tmp_path / "runs.csv"
    with open(runs, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    done = _offline_primary(runs, "--out", tmp_path / "p", "--versus", "gem-se:gem")
    assert done.returncode == 0, done.stderr
    [row] = list(csv.DictReader(open(tmp_path / "p_versus.csv")))
    assert (row["model"], row["versus"], row["n_pairs"], row["n_lower"]) == ("gem-se", "gem", "5", "0")
    bad = _offline_primary(runs, "--out", tmp_path / "p", "--versus", "gem-se")
    assert bad.returncode == 2 and "--versus takes MODEL:OTHER" in bad.stderr


def test_offline_primary_script_with_the_studies_levels_reproduces_their_primary_files(tmp_path):
    """``--levels PRIMARY.csv``: the committed 3-data-set study's runs with its own levels give its primary.csv
    (written by pets.compare offline from the data) value for value; a file that is not a primary.csv is refused."""
    runs, primary = RESULTS / "paper_data3_runs.csv", RESULTS / "paper_data3_primary.csv"
    done = _offline_primary(runs, "--levels", primary, "--out", tmp_path / "p")
    assert done.returncode == 0, done.stderr
    got, want = (list(csv.DictReader(open(f))) for f in (tmp_path / "p.csv", primary))
    assert got == want and any(float(r["level"]) != math.sqrt(2) for r in got)
    bad = _offline_primary(runs, "--levels", runs, "--out", tmp_path / "q")
    assert bad.returncode == 2 and "not a primary.csv" in bad.stderr


def test_gem_se_studys_committed_primary_and_versus_files_are_what_the_documented_command_gives(tmp_path):
    """docs/results.md's command for the gem-se study (issue 32) regenerates its committed primary, past-level and
    versus (gem-se / gem) files from its committed runs, byte for byte."""
    done = _offline_primary(RESULTS / "paper_gemse_runs.csv", "--levels", RESULTS / "paper_gemse_primary.csv",
                            "--versus", "gem-se:gem", "--out", tmp_path / "p")  # fmt: skip
    assert done.returncode == 0, done.stderr
    for suffix in ("", "_past_level", "_versus"):
        got = (tmp_path / f"p{suffix}.csv").read_bytes()
        assert got == (RESULTS / f"paper_gemse_primary{suffix}.csv").read_bytes(), suffix


def test_fig2_averages_over_the_tracking_horizons_only() -> None:
    """Issue 37: Fig. 2 (relative_error.csv) averages each run's error over delta's tracking horizons, the
    primary endpoint's; a run past the level only at a later horizon stays in; with no delta run, every horizon."""
    from pets.experiments.studies.offline import summary_from_runs

    level = math.sqrt(2)
    rng = np.random.default_rng(0)
    rows, mean_step = [], {}
    for model in ("delta", "gem"):
        for seed in range(4):
            for h, std in ((1, 0.2), (5, 0.9), (10, 3.0)):  # delta's median passes the level at h=10
                mean_step[model, seed, h] = float(rng.uniform(1, 2))
                err = {"standardized_error": std * (1 + 0.1 * seed), "mean_step_error": mean_step[model, seed, h]}
                rows.append({"env": "reacher", "model": model, "seed": str(seed), "horizon": str(h), **err})
    _, relative = summary_from_runs(rows, level)
    gem = next(r for r in relative if r["model"] == "gem" and r["metric"] == "mean_step_error")
    assert gem["horizons"] == "1 5" and (gem["n_seeds"], gem["n_diverged"]) == (4, 0)
    averaged = [np.mean([mean_step["gem", s, h] for h in (1, 5)]) for s in range(4)]
    assert gem["iqm"] == pytest.approx(scipy.stats.trim_mean(averaged, 0.25), rel=1e-12)
    ratios = [a / np.mean([mean_step["delta", s, h] for h in (1, 5)]) for s, a in enumerate(averaged)]
    assert gem["ratio_to_delta"] == pytest.approx(scipy.stats.trim_mean(ratios, 0.25), rel=1e-12)
    _, no_delta = summary_from_runs([r for r in rows if r["model"] == "gem"], level)
    assert {r["horizons"] for r in no_delta} == {"1 5 10"}
    assert all(r["n_diverged"] == 4 for r in no_delta)  # every run is past the level at h=10: out of the average
