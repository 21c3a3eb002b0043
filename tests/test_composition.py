"""The composition study's analysis (pets.experiments.studies.composition, issue 53): its primary family against
delta-groupfeat, its secondary endpoints and its generated files, against scipy and hand-computed values."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.stats

from pets.experiments.statistics import holm
from pets.experiments.studies import composition

HORIZONS = (1, 5, 10, 25, 50)
LEVEL = 1.0


def _rows(env: str, model: str, errors: dict[tuple[int, int], list[float]], rotation: float = 0.1) -> list[dict]:
    """Rows as composition_runs.csv has them: {(data seed, seed): [standardized error per horizon]}; the rotation
    error is ``rotation`` times the standardized error."""
    name = {0: f"{env}-test.npz", 1: f"{env}-d1-test.npz", 2: f"{env}-d2-test.npz"}
    return [
        {"env": env, "model": model, "data": name[d], "seed": s, "horizon": h, "standardized_error": e,
         "rotation_error": rotation * e}
        for (d, s), errs in errors.items()
        for h, e in zip(HORIZONS, errs)
    ]  # fmt: skip


RUNS = [(d, s) for d in (0, 1) for s in range(3)]  # 2 data sets x 3 seeds: 6 pairs
BASE = {r: [0.2 * (1 + r[1] / 10), 0.4, 0.6, 0.8, 1.2] for r in RUNS}  # tracking horizons 1-25 at level 1


def _study(gem_scale: float, se_scale: float, delta: list[float] | None = None) -> list[dict]:
    gem = {r: [gem_scale * e for e in errs] for r, errs in BASE.items()}
    se = {r: [se_scale * (1 + r[1] / 20) * e for e in errs] for r, errs in BASE.items()}
    d = {r: delta or [0.3, 0.5, 0.7, 0.9, 0.95] for r in RUNS}
    return (_rows("ant", "delta-groupfeat", BASE) + _rows("ant", "gem", gem) + _rows("ant", "gem-se", se)
            + _rows("ant", "delta", d))  # fmt: skip


def _clipped(errs: list[float], hs=HORIZONS[:4]) -> float:
    return float(np.mean([min(errs[HORIZONS.index(h)], LEVEL) for h in hs]))


def test_the_data_set_is_read_from_the_test_files_name():
    assert [composition.data_seed(n) for n in ("ant-test.npz", "ant-d1-test.npz", "humanoid-d12-test.npz")] == [
        0,
        1,
        12,
    ]


def test_the_primary_family_is_gem_and_gem_se_against_delta_groupfeat_with_holm_over_the_registered_four():
    rows = _study(0.9, 1.05) + [{**r, "env": "humanoid"} for r in _study(0.95, 0.97)]
    levels = {"ant": (LEVEL, "given"), "humanoid": (LEVEL, "given")}
    primary = composition.primary_rows(rows, levels)
    assert [(r["env"], r["model"]) for r in primary] == [
        (e, m) for e in ("ant", "humanoid") for m in ("delta-groupfeat", "gem", "gem-se")
    ]  # delta is not in the family
    by = {(r["env"], r["model"]): r for r in primary}
    se = by["ant", "gem-se"]
    assert se["tracking_horizons"] == "1 5 10 25" and se["n_pairs"] == 6 and se["n_data_sets"] == 2
    ratios = [_clipped([1.05 * (1 + s / 20) * e for e in BASE[d, s]]) / _clipped(BASE[d, s]) for d, s in RUNS]
    exact = scipy.stats.permutation_test((np.log(ratios),), np.mean, permutation_type="samples", n_resamples=np.inf)
    assert se["p_value_exact"] == pytest.approx(exact.pvalue)
    assert se["ratio_ci_low"] <= se["ratio_to_delta"] <= se["ratio_ci_high"]
    tested = [by[e, m]["p_value_exact"] for e in ("ant", "humanoid") for m in ("gem", "gem-se")]
    assert [by[e, m]["p_value_holm"] for e in ("ant", "humanoid") for m in ("gem", "gem-se")] == holm(tested)
    assert by["ant", "gem"]["ratio_to_delta"] == pytest.approx(0.9)  # every pair 0.9: the IQM is 0.9


def test_a_test_of_the_family_not_yet_run_enters_holm_with_p_1():
    """Ant alone (Humanoid not yet run): Holm over the registered 4, Humanoid's two tests at p = 1 (statsmodels);
    an upper bound on the Holm p that Ant's tests get once Humanoid's real p-values join, whatever they are."""
    from statsmodels.stats.multitest import multipletests

    levels = {"ant": (LEVEL, "given"), "humanoid": (LEVEL, "given")}
    ant = {r["model"]: r for r in composition.primary_rows(_study(0.9, 0.8), levels)}
    exact = [ant["gem"]["p_value_exact"], ant["gem-se"]["p_value_exact"]]
    assert max(exact) < 0.05  # every pair lower: both significant alone, so the family's size decides
    assert [ant["gem"]["p_value_holm"], ant["gem-se"]["p_value_holm"]] == pytest.approx(
        multipletests([*exact, 1.0, 1.0], method="holm")[1][:2]
    )
    assert ant["gem"]["p_value_holm"] > multipletests(exact, method="holm")[1][0]  # not Holm over the 2 present
    for humanoid in ((0.9, 0.8), (1.2, 1.2)):  # Humanoid's tests significant, then not
        rows = _study(0.9, 0.8) + [{**r, "env": "humanoid"} for r in _study(*humanoid)]
        full = {(r["env"], r["model"]): r for r in composition.primary_rows(rows, levels)}
        assert all(full["ant", m]["p_value_holm"] <= ant[m]["p_value_holm"] for m in ("gem", "gem-se"))


def test_rotation_secondary_reads_the_primarys_horizons_and_counts_a_diverged_run_as_every_angle_pi():
    rows = _study(0.9, 1.0)
    for r in rows:  # gem's data set 1, seed 2 diverges in rotation at h = 10
        if (r["model"], r["data"], r["seed"], r["horizon"]) == ("gem", "ant-d1-test.npz", 2, 10):
            r["rotation_error"] = math.nan
    worst = composition.worst_rotation("ant")
    assert worst == pytest.approx(math.pi * 3)  # the torso's SO(3) and 8 hinges: sqrt(9) angles of pi
    rot = {r["model"]: r for r in composition.secondary_rows(rows, {"ant": (LEVEL, "given")})
           if r["endpoint"] == "rotation_error"}  # fmt: skip
    assert set(rot) == {"gem", "gem-se"} and rot["gem"]["horizons"] == "1 5 10 25"
    gem = [0.1 * 0.9 * np.array(BASE[r][:4]) for r in RUNS]
    gem[-1][2] = worst
    ratios = [np.mean(g) / np.mean(0.1 * np.array(BASE[r][:4])) for g, r in zip(gem, RUNS)]
    assert rot["gem"]["n_lower"] == 5 and rot["gem"]["n_pairs"] == 6
    exact = scipy.stats.permutation_test((np.log(ratios),), np.mean, permutation_type="samples", n_resamples=np.inf)
    assert rot["gem"]["p_value_exact"] == pytest.approx(exact.pvalue)


def test_long_horizon_is_gem_over_delta_at_h50_only_where_delta_still_tracks():
    levels = {"ant": (LEVEL, "given")}
    [tracks] = [r for r in composition.secondary_rows(_study(0.9, 1.0), levels) if r["endpoint"].endswith("50")]
    assert (tracks["model"], tracks["versus"], tracks["horizons"]) == ("gem", "delta", "50")
    ratios = [min(1.2 * 0.9, LEVEL) / 0.95 for _ in RUNS]  # gem's h=50 error clipped at the level
    assert tracks["ratio"] == pytest.approx(ratios[0]) and tracks["n_pairs"] == 6 and tracks["note"] == ""
    lost = _study(0.9, 1.0, delta=[0.3, 0.5, 0.7, 0.9, 1.5])  # delta past the level at h = 50
    [row] = [r for r in composition.secondary_rows(lost, levels) if r["endpoint"].endswith("50")]
    assert "no longer tracks at h = 50" in row["note"] and "ratio" not in row


def test_levels_are_the_mean_of_the_data_sets():
    rows = [{"env": "ant", "data_seed": "0", "level": "1.2"}, {"env": "ant", "data_seed": "1", "level": "1.4"}]
    level, source = composition.env_levels(rows)["ant"]
    assert level == pytest.approx(1.3) and source == "mean of data sets 0, 1"


def _commit(results: Path, rows: list[dict], levels: str) -> None:
    """The study's committed inputs in ``results``: its runs and its levels' rows (``levels``, after the header)."""
    with open(results / composition.RUNS, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (results / composition.LEVELS).write_text("env,data_seed,level\n" + levels)


def test_the_products_and_the_block_are_made_from_the_committed_rows_only(tmp_path: Path):
    results, figures = tmp_path / "docs" / "results", tmp_path / "docs" / "figures"
    results.mkdir(parents=True)
    _commit(results, _study(0.9, 1.05), "ant,0,1.0\nant,1,1.0\n")
    composition.write_products(results, figures)
    assert all((results / name).is_file() for name in composition.OUTPUTS) and (figures / composition.FIGURE).is_file()
    with open(results / "composition_summary.csv", newline="") as f:
        summary = list(csv.DictReader(f))
    assert {r["model"] for r in summary} == {"delta", "delta-groupfeat", "gem", "gem-se"}  # each against delta
    block = composition.study_table(tmp_path)
    assert "| ant | gem | 6 (2) | 1 5 10 25 | 0.9 [0.9, 0.9] |" in block
    assert "| standardized_error at h = 50 | ant | gem / delta | 6 (2) |" in block


def test_a_run_without_its_envs_level_is_named(tmp_path: Path):
    _commit(tmp_path, _study(0.9, 1.0), "humanoid,0,1.4\n")
    with pytest.raises(ValueError, match=r"composition_levels.csv: no level for ant \(partial_offline_runs.py"):
        composition.write_products(tmp_path, tmp_path)


def _answer(tmp_path: Path, rows: list[dict]) -> str:
    """The answer line from the primary family as the report writes it (a CSV file) and the answer table reads it."""
    from pets.experiments.report import read_csv_rows, write_csv
    from pets.experiments.studies.primary import PRIMARY_COLUMNS

    levels = {"ant": (LEVEL, "given"), "humanoid": (LEVEL, "given")}
    write_csv(tmp_path / "primary.csv", composition.primary_rows(rows, levels), PRIMARY_COLUMNS)
    return composition.answer_line(read_csv_rows(tmp_path / "primary.csv"))


def test_the_answer_line_words_each_env_by_the_registered_rule_once_both_arms_have_15_pairs(tmp_path: Path):
    full = [(d, s) for d in (0, 1, 2) for s in range(5)]  # the registered 15 pairs
    base = {r: [0.2 * (1 + r[1] / 10), 0.4 + 0.01 * r[0], 0.6, 0.8, 1.2] for r in full}

    def env(name: str, gem: float, se: float, runs=full) -> list[dict]:
        sign = {r: 1 if (r[0] + r[1]) % 2 else -1 for r in runs}  # mixed: no difference shown
        scaled = {m: {r: [(s if s != 1.0 else 1 + 0.05 * sign[r]) * e for e in base[r]] for r in runs}
                  for m, s in (("gem", gem), ("gem-se", se))}  # fmt: skip
        return (_rows(name, "delta-groupfeat", {r: base[r] for r in runs}) + _rows(name, "gem", scaled["gem"])
                + _rows(name, "gem-se", scaled["gem-se"]))  # fmt: skip

    line = _answer(tmp_path, env("ant", 0.9, 1.0) + env("humanoid", 1.0, 1.0))
    assert line.startswith("**Inputs or composition** (the composition study, docs/studies/composition.md:")
    ant, humanoid = line.split("): ", 1)[1].split("; humanoid: ")
    # every pair lower: exact p 2 / 2**15, Holm over the 4 tests 4x that
    assert ant.startswith("ant: **composition adds beyond the inputs** (gem / delta-groupfeat 0.9 [0.9, 0.9], "
                          "Holm p 0.000244; gem-se / delta-groupfeat ")  # fmt: skip
    assert humanoid.startswith("**no difference shown** (gem / delta-groupfeat ")
    line = _answer(tmp_path, env("ant", 1.0, 1.1) + env("humanoid", 1.0, 1.0))
    assert "ant: **composition costs** (gem / delta-groupfeat " in line and ", Holm p 1;" in line
    short = [(d, s) for d in (0, 1) for s in range(5)]
    line = _answer(tmp_path, env("ant", 0.9, 0.9, runs=short))
    assert line.endswith(
        "ant: not yet (pairs of 15: gem 10, gem-se 10); humanoid: not yet (pairs of 15: gem 0, gem-se 0)."
    )
