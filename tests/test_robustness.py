"""The offline verdicts' robustness checks as generated tables (pets.experiments.offline_tables): the primary endpoint
of each data set alone, recomputed here from the committed per-run rows with scipy; the 5x rerun's pre-registered
rule; the learning curves' checkpoints as pandas reads them."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from scipy.stats import trim_mean

from pets.experiments import published
from pets.experiments.offline_tables import _rule, curves_table
from pets.experiments.report import read_csv_rows
from pets.experiments.studies.primary import PER_DATA_SET_COLUMNS, per_data_set_rows

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / published.RESULTS


def test_each_data_sets_primary_is_the_trimmed_mean_of_its_pairs_endpoint_ratios() -> None:
    runs = read_csv_rows(RESULTS / "paper_data3_runs.csv")
    level = published.DATA_LEVELS["ant"]
    rows = per_data_set_rows([r for r in runs if r["env"] == "ant"], {"ant": (level, "data")})
    for d in (0, 1, 2):
        gem = next(r for r in rows if r["data_seed"] == d and r["model"] == "gem")
        hs = [int(h) for h in gem["tracking_horizons"].split()]
        err = {
            (r["model"], int(r["seed"]), int(r["horizon"])): float(r["standardized_error"])
            for r in runs
            if r["env"] == "ant" and int(r["data_seed"]) == d
        }

        endpoint = {(m, s): sum(min(err[(m, s, h)], level) for h in hs) / len(hs) for m, s, _ in err}
        ratios = [endpoint[("gem", s)] / endpoint[("delta", s)] for s in range(5)]
        assert gem["ratio_to_delta"] == pytest.approx(trim_mean(ratios, 0.25), rel=1e-12)
        assert gem["n_pairs"] == 5
        all_one_way = all(r < 1 for r in ratios) or all(r > 1 for r in ratios)
        assert (gem["p_value_exact"] == pytest.approx(1 / 16)) == all_one_way


def test_the_per_data_set_file_carries_no_holm_step_nor_verdict() -> None:
    """A secondary, uncorrected comparison: no family-wise step is published beside it."""
    header = (RESULTS / "paper_data3_per_data_set.csv").read_text().split("\n")[0].split(",")
    assert header == PER_DATA_SET_COLUMNS and "p_value_holm" not in header and "verdict" not in header


def _ratio(value: float, low: float, high: float) -> dict[str, str]:
    return {"ratio_to_delta": str(value), "ratio_ci_low": str(low), "ratio_ci_high": str(high)}


def test_the_5x_rule_changes_the_verdict_on_a_side_flip_or_a_ci_that_excludes_the_10k_ratio() -> None:
    short = _ratio(0.96, 0.95, 0.97)
    assert _rule(_ratio(0.955, 0.948, 0.99), short) == "does not change"
    assert _rule(_ratio(1.02, 0.95, 1.05), short) == "changes"  # the other side of 1
    assert _rule(_ratio(0.90, 0.88, 0.93), short) == "changes"  # the CI excludes 0.96


def test_the_curves_table_gives_the_median_over_seeds_at_each_checkpoint() -> None:
    curves = pd.read_csv(RESULTS / "learning_curves_50k.csv")
    row = next(line for line in curves_table(ROOT).split("\n") if line.startswith("| ant | gem | 5 "))
    at = curves[(curves.env == "ant") & (curves.model == "gem")].groupby("step").holdout_error.median()
    cells = row.split(" | ")[4].split(" / ")
    assert [float(c) for c in cells] == pytest.approx([at[10000], at[40000], at[50000]], rel=2e-3)
