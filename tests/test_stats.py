"""pets.experiments.statistics: the A/B statistics against rliable's own functions on fixed inputs and hand-computed
cases; pets.stats.bootstrap: the mean bootstrap against exact small cases, scipy's bootstrap and trim_mean,
and a normal-theory CI."""

import math

import numpy as np
import pytest
import scipy.stats
from rliable import library, metrics

from pets.experiments.statistics import (
    DIVERGED_STANDARDIZED_ERROR,
    SIGN_FLIP_DRAWS,
    ci_exact_note,
    divergence,
    divergences,
    holm,
    iqm_ci,
    iqm_ci_finite,
    iqm_columns,
    p_improvement,
    p_improvement_ci,
    p_lower_columns,
    paired_differences,
    paired_ratios,
    sign_flip_p,
)
from pets.stats import stratified
from pets.stats.bootstrap import bootstrap_band, bootstrap_ci, iqm, summarise

INF, NAN = math.inf, math.nan


# --------------------------------------------------------------------------- A/B statistics (rliable)
def rliable_iqm_per_column(scores):
    return np.array([metrics.aggregate_iqm(scores[:, j]) for j in range(scores.shape[1])])


def rliable_p_per_column(x, y):
    """rliable's P(X > Y) of each column (higher is better: pass negated errors)."""
    return np.array([metrics.probability_of_improvement(x[:, [j]], y[:, [j]]) for j in range(x.shape[1])])


@pytest.mark.parametrize("n", range(1, 12))
def test_iqm_columns_is_rliable_aggregate_iqm_of_each_column(n):
    x = np.random.default_rng(n).standard_cauchy(size=(n, 6))
    np.testing.assert_array_equal(iqm_columns(x), rliable_iqm_per_column(x))


@pytest.mark.parametrize("shape, seed", [((5, 4), 3), ((3, 2), 0), ((8, 7), 11), ((1, 3), 5)])
def test_iqm_ci_is_rliables_interval_estimate(shape, seed):
    x = np.random.default_rng(seed).gamma(2.0, 3.0, size=shape)
    np.random.seed(12345)
    before = np.random.get_state()[1].copy()
    point, low, high = iqm_ci(x, reps=300, seed=seed)
    np.testing.assert_array_equal(np.random.get_state()[1], before)  # the global generator is left as it was
    np.random.seed(seed)
    ref_point, ref_interval = library.get_interval_estimates({"x": x}, rliable_iqm_per_column, reps=300)
    np.testing.assert_array_equal(point, ref_point["x"])
    np.testing.assert_array_equal(low, ref_interval["x"][0])
    np.testing.assert_array_equal(high, ref_interval["x"][1])
    assert (low <= point).all() and (point <= high).all()
    assert iqm_ci(x, reps=300, seed=seed)[1].tolist() == low.tolist()  # reproducible


@pytest.mark.parametrize("block_elements", [2_000_000, 50])  # 50: the replications drawn in many blocks
@pytest.mark.parametrize("runs, columns, reps", [(5, 1, 1000), (15, 3, 400), (34, 1, 300), (10, 8, 257), (1, 2, 50)])
def test_stratified_percentile_ci_is_rliables_interval_estimate_bit_for_bit(runs, columns, reps, block_elements):
    """All replications at once: rliable's numbers (its own bootstrap, arch's loop) and its use of the global
    generator, for one array and for two resampled independently with different numbers of runs."""
    rng = np.random.default_rng(runs * 100 + columns)
    x = np.round(rng.standard_cauchy(size=(runs, columns)), 2)  # rounded: ties, as seeds' rewards can have
    y = np.round(rng.normal(size=(runs + 3, columns)), 1)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(stratified, "_BLOCK_ELEMENTS", block_elements)
        for arrays, func, key in [([x], iqm_columns, "x"), ([-x, -y], p_lower_columns, "p")]:
            np.random.seed(runs)
            point, low, high = stratified.stratified_percentile_ci(arrays, func, reps=reps, confidence=0.9)
            after = np.random.get_state()[1].copy()
            np.random.seed(runs)
            scores = arrays[0] if len(arrays) == 1 else arrays
            ref_point, ref_interval = library.get_interval_estimates(
                {key: scores}, func, reps=reps, confidence_interval_size=0.9
            )
            np.testing.assert_array_equal(np.random.get_state()[1], after)  # the same draws, no more, no fewer
            np.testing.assert_array_equal(point, ref_point[key])
            np.testing.assert_array_equal(low, ref_interval[key][0])
            np.testing.assert_array_equal(high, ref_interval[key][1])


@pytest.mark.parametrize("values", [[1.0, 4.0, 10.0], [2.0, 7.0], [5.0]])
def test_with_three_seeds_or_fewer_the_ci_is_min_to_max(values):
    # the all-min and all-max resamples have probability n**-n >= 1/27 > 2.5 %
    point, low, high = iqm_ci(np.array(values)[:, None], reps=2000)
    assert point[0] == pytest.approx(np.mean(values))
    assert (low[0], high[0]) == (min(values), max(values))


def test_iqm_ci_refuses_non_finite_scores_and_bad_settings():
    for bad in (INF, NAN):
        with pytest.raises(ValueError, match="diverged"):
            iqm_ci([[1.0, 2.0], [bad, 3.0]])
    with pytest.raises(ValueError, match="shape"):
        iqm_ci(np.empty((0, 3)))
    with pytest.raises(ValueError, match="reps"):
        iqm_ci([[1.0]], reps=0)


def test_p_improvement_hand_computed_with_ties_counting_half():
    # pairs x < y: (1,2) (1,3) (1,4) (2,3) (2,4) (3,4) = 6; ties (2,2) (3,3) = 2 -> (6 + 1) / 9
    assert p_improvement([1, 2, 3], [2, 3, 4]) == pytest.approx(7 / 9)
    assert p_improvement([2, 3, 4], [1, 2, 3]) == pytest.approx(2 / 9)
    assert p_improvement([5.0, 5.0], [5.0, 5.0, 5.0]) == 0.5
    # diverged runs (NaN / inf) are +inf: they lose to every finite run and tie with each other
    # x = [1, inf, 3], y = [2, 3, inf]: wins 1<2, 1<3, 1<inf, 3<inf = 4; ties 3=3, inf=inf = 2 -> 5 / 9
    assert p_improvement([1, NAN, 3], [2, 3, INF]) == pytest.approx(5 / 9)
    assert p_improvement([NAN, INF], [1e9]) == 0.0
    assert p_improvement([1e9], [INF]) == 1.0
    assert p_improvement([INF, INF], [NAN]) == 0.5


def test_p_improvement_is_rliables_probability_of_improvement_on_negated_errors():
    rng = np.random.default_rng(4)
    x, y = rng.gamma(2.0, 1.0, size=7), rng.gamma(2.0, 1.2, size=5)
    x[2] = INF
    expected = metrics.probability_of_improvement(-x[:, None], -y[:, None])
    assert p_improvement(x, y) == expected


def test_p_improvement_ci_is_rliables_interval_estimate():
    rng = np.random.default_rng(5)
    x, y = rng.gamma(2.0, 1.0, size=(5, 3)), rng.gamma(2.0, 1.3, size=(4, 3))
    x[1] = NAN  # a diverged run of the model: +inf in every column
    point, low, high = p_improvement_ci(x, y, reps=200, seed=7)
    neg_x, neg_y = -np.where(np.isfinite(x), x, INF), -y
    np.random.seed(7)
    ref_point, ref_interval = library.get_interval_estimates({"p": [neg_x, neg_y]}, rliable_p_per_column, reps=200)
    np.testing.assert_array_equal(point, ref_point["p"])
    np.testing.assert_array_equal(low, ref_interval["p"][0])
    np.testing.assert_array_equal(high, ref_interval["p"][1])
    for j in range(3):
        assert point[j] == p_improvement(x[:, j], y[:, j])
    assert ((0 <= low) & (low <= point) & (point <= high) & (high <= 1)).all()


def test_p_improvement_of_rewards_is_rliables_probability_of_improvement_on_the_rewards():
    # higher is better: P(X > Y) + P(X = Y) / 2, rliable's function on the rewards themselves (not negated)
    assert p_improvement([1, 2, 3], [2, 3, 4], higher_is_better=True) == pytest.approx(2 / 9)
    assert p_improvement([2, 3, 4], [1, 2, 3], higher_is_better=True) == pytest.approx(7 / 9)
    rng = np.random.default_rng(6)
    x, y = rng.normal(0.0, 50.0, size=6), rng.normal(-20.0, 50.0, size=5)  # rewards can be negative
    assert p_improvement(x, y, higher_is_better=True) == metrics.probability_of_improvement(x[:, None], y[:, None])
    assert p_improvement(x, y, higher_is_better=True) == p_improvement(-x, -y)
    # diverged runs (NaN / +-inf) are the worst reward, -inf: they lose to every finite run, tie with each other
    assert p_improvement([NAN, INF], [-1e9], higher_is_better=True) == 0.0
    assert p_improvement([-1e9], [NAN], higher_is_better=True) == 1.0
    assert p_improvement([NAN, -INF], [INF], higher_is_better=True) == 0.5
    x[1] = NAN
    expected = metrics.probability_of_improvement(np.where(np.isnan(x), -INF, x)[:, None], y[:, None])
    assert p_improvement(x, y, higher_is_better=True) == expected


def test_p_improvement_ci_of_rewards_is_rliables_interval_estimate():
    rng = np.random.default_rng(8)
    x, y = rng.normal(1.0, 2.0, size=(5, 2)), rng.normal(0.0, 2.0, size=(6, 2))
    x[3] = NAN  # a diverged run: reward -inf
    point, low, high = p_improvement_ci(x, y, higher_is_better=True, reps=200, seed=3)
    np.random.seed(3)
    ref_point, ref_interval = library.get_interval_estimates(
        {"p": [np.where(np.isfinite(x), x, -INF), y]}, rliable_p_per_column, reps=200
    )
    np.testing.assert_array_equal(point, ref_point["p"])
    np.testing.assert_array_equal(low, ref_interval["p"][0])
    np.testing.assert_array_equal(high, ref_interval["p"][1])
    p1, low1, high1 = p_improvement_ci(x[:, 0], y[:, 0], higher_is_better=True, reps=200, seed=3)  # 1-D: one column
    assert p1[0] == point[0] == p_improvement(x[:, 0], y[:, 0], higher_is_better=True)
    assert ((0 <= low) & (low <= point) & (point <= high) & (high <= 1)).all()


def test_paired_differences_use_the_seeds_both_have():
    model = {0: 5.0, 1: -3.0, 4: 7.0}
    baseline = {1: -4.5, 0: 6.0, 2: 0.0}
    seeds, diffs = paired_differences(model, baseline)
    assert seeds == [0, 1] and diffs.shape == (2, 1)
    np.testing.assert_array_equal(diffs[:, 0], [-1.0, 1.5])
    seeds, diffs = paired_differences({3: [1.0, 2.0]}, {3: [0.5, 4.0]})
    np.testing.assert_array_equal(diffs, [[0.5, -2.0]])
    assert paired_differences({0: 1.0}, {1: 1.0})[0] == []


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n", [2, 3, 5, 8])
def test_sign_flip_p_is_scipys_exact_paired_permutation_test(n, seed):
    rng = np.random.default_rng(seed)
    x, y = rng.normal(0.3, 1.0, n), rng.normal(0.0, 1.0, n)
    ref = scipy.stats.permutation_test(
        (x, y), lambda a, b, axis: np.mean(a - b, axis=axis), permutation_type="samples", n_resamples=np.inf
    )
    assert sign_flip_p(x - y) == pytest.approx(ref.pvalue, rel=1e-12)


def test_sign_flip_p_hand_computed_cases():
    assert sign_flip_p([1.0, 2.0, 3.0, 4.0, 5.0]) == 2 / 32  # the smallest p five pairs can give
    assert sign_flip_p([1.0, -2.0, 3.0, 4.0, 5.0]) == 6 / 32  # |mean| >= 2.2: the two all-same-sign, +-1, +-(1, 2)
    assert sign_flip_p([0.0, 0.0, 0.0]) == 1.0
    assert sign_flip_p([-7.0]) == 1.0  # one pair: both signs are as extreme
    assert sign_flip_p([0.1, 0.2, 0.3]) == sign_flip_p([0.1 * 3, 0.2 * 3, 0.3 * 3])  # ties by float rounding
    assert math.isnan(sign_flip_p([]))
    with pytest.raises(ValueError, match="finite"):
        sign_flip_p([1.0, NAN])


@pytest.mark.parametrize("seed", range(3))
def test_sign_flip_p_monte_carlo_above_16_pairs_is_within_its_error_of_scipys_exact_test(seed):
    rng = np.random.default_rng(seed)
    x, y = rng.normal(0.4, 1.0, 17), rng.normal(0.0, 1.0, 17)  # 17 pairs: sampled here, enumerated by scipy
    exact = scipy.stats.permutation_test(
        (x, y), lambda a, b, axis: np.mean(a - b, axis=axis), permutation_type="samples", n_resamples=np.inf
    ).pvalue
    p = sign_flip_p(x - y, seed=seed)
    assert abs(p - exact) < 4 * math.sqrt(exact * (1 - exact) / SIGN_FLIP_DRAWS) + 2 / SIGN_FLIP_DRAWS
    assert sign_flip_p(x - y, seed=seed) == p  # seeded
    assert sign_flip_p(np.ones(40)) == 1 / (1 + SIGN_FLIP_DRAWS)  # no random pattern is as extreme


def test_ci_exact_note_flags_a_bootstrap_ci_that_a_5_pair_exact_test_does_not_back():
    """Five paired differences all positive: rliable's stratified-bootstrap IQM CI excludes 0, scipy's exact
    permutation test gives p = 0.0625: a note. Ten all positive: p = 0.002 and the CI excludes 0: they agree."""
    for n, expected_note in ((5, True), (10, False)):
        d = np.linspace(1.0, 2.0, n)
        exact = scipy.stats.permutation_test((d,), np.mean, permutation_type="samples", n_resamples=np.inf).pvalue
        (_,), (low,), (high,) = iqm_ci(d[:, None], reps=2000, seed=0)
        assert low > 0 and sign_flip_p(d) == pytest.approx(exact)
        note = ci_exact_note(low, high, 0.0, sign_flip_p(d))
        assert bool(note) is expected_note
    note = "the bootstrap CI excludes 1, the exact p is 0.0625: not significant at 0.05"
    assert ci_exact_note(0.5, 0.9, 1.0, 0.0625) == note
    assert ci_exact_note(-0.1, 0.3, 0.0, 0.01) == "the exact p is 0.01 but the bootstrap CI contains 0"
    assert ci_exact_note(0.1, 0.3, 0.0, 0.01) == ci_exact_note(-0.1, 0.3, 0.0, 0.2) == ""  # agreement
    assert ci_exact_note(None, 0.3, 0.0, 0.01) == ci_exact_note(0.1, 0.3, 0.0, NAN) == ""  # nothing to compare


def test_holm_is_statsmodels_holm():
    from statsmodels.stats.multitest import multipletests

    rng = np.random.default_rng(0)
    for m in (1, 2, 4, 9):
        p = rng.uniform(0, 0.2, m)
        np.testing.assert_allclose(holm(p), multipletests(p, method="holm")[1], rtol=1e-12)
    got = holm([0.01, NAN, 0.04, 0.03])  # NaN: no test, not counted in the family
    np.testing.assert_allclose(got[:1] + got[2:], multipletests([0.01, 0.04, 0.03], method="holm")[1])
    assert math.isnan(got[1])


def test_paired_ratios_use_the_seeds_both_have_and_drop_undefined_columns():
    model = {0: [2.0, 1.0, 3.0], 1: [3.0, 0.0, 1.0], 3: [9.0, 9.0, 9.0]}
    delta = {1: [2.0, 0.0, 4.0], 0: [1.0, 1.0, 2.0], 2: [5.0, 5.0, 5.0]}
    seeds, ratios = paired_ratios(model, delta)
    assert seeds == [0, 1]
    np.testing.assert_array_equal(ratios[:, 0], [2.0, 1.5])
    np.testing.assert_array_equal(ratios[:, 2], [1.5, 0.25])
    assert np.isnan(ratios[:, 1]).all()  # 0 / 0 for seed 1: undefined for every seed
    assert paired_ratios({0: [1.0]}, {1: [1.0]})[0] == []
    point, low, high = iqm_ci(ratios[:, [0, 2]], reps=200)
    np.testing.assert_array_equal(point, [1.75, 0.875])  # n = 2: the IQM is the mean


def test_paired_ratios_leave_out_the_pairs_where_either_run_diverged():
    model = {0: [2.0, NAN, 1.0], 1: [3.0, 4.0, 1.0], 2: [4.0, 6.0, 5.0]}
    delta = {0: [1.0, 2.0, 0.0], 1: [INF, 2.0, 2.0], 2: [2.0, 3.0, 5.0]}
    seeds, ratios = paired_ratios(model, delta)
    assert seeds == [0, 1, 2]
    np.testing.assert_array_equal(ratios[:, 0], [2.0, NAN, 2.0])  # seed 1: delta diverged there
    np.testing.assert_array_equal(ratios[:, 1], [NAN, 2.0, 2.0])  # seed 0: the model diverged there
    assert np.isnan(ratios[:, 2]).all()  # delta's error 0 for seed 0 (both finite): undefined for every seed


def test_iqm_ci_finite_is_iqm_ci_over_the_finite_runs_of_each_column():
    x = np.random.default_rng(4).gamma(2.0, 3.0, size=(6, 5))
    all_finite = iqm_ci(x, reps=300, seed=2)
    for got, want in zip(iqm_ci_finite(x, reps=300, seed=2), all_finite):
        np.testing.assert_array_equal(got, want)  # every value finite: one iqm_ci call, the same numbers
    x[1, [1, 3]] = NAN  # run 1 left out of columns 1 and 3 (one call for both)
    x[4, 2] = INF
    x[:, 4] = NAN  # no run left
    point, low, high = iqm_ci_finite(x, reps=300, seed=2)
    for cols, rows in (([0], [0, 1, 2, 3, 4, 5]), ([1, 3], [0, 2, 3, 4, 5]), ([2], [0, 1, 2, 3, 5])):
        want = iqm_ci(x[np.ix_(rows, cols)], reps=300, seed=2)
        for got, w in zip((point, low, high), want):
            np.testing.assert_array_equal(got[cols], w)
    np.testing.assert_array_equal(point[1], metrics.aggregate_iqm(np.delete(x[:, 1], 1)))
    assert np.isnan([point[4], low[4], high[4]]).all()


def test_divergence_non_finite_values_and_the_standardized_threshold():
    ok = {"mean_step_error": 0.1, "standardized_error": 2.0, "nonfinite_fraction": 0.0}
    assert divergence(ok) is None
    assert divergence({**ok, "mean_step_error": NAN}) == "mean_step_error nan"
    assert divergence({"rotation_error": INF}) == "rotation_error inf"
    assert (
        divergence({"mean_step_error": 1.0, "nonfinite_fraction": 0.01}) == "non-finite predictions (0.01 of the steps)"
    )
    assert divergence({"standardized_error": DIVERGED_STANDARDIZED_ERROR}) is None  # the threshold itself is not
    assert divergence({"standardized_error": 7e4, "mean_step_error": 3.0}) == "standardized_error 7e+04 > 100"
    assert divergence({"mean_step_error": 7e4, "position_error": 1e5}) is None  # old keys: non-finite only


def test_divergences_are_per_horizon():
    ok = {"mean_step_error": 0.1, "standardized_error": 2.0, "nonfinite_fraction": 0.0}
    assert divergences({"1": ok, "5": ok}) == {}
    bad = {"1": ok, "5": {**ok, "standardized_error": 7e4}, "10": ok, "50": {**ok, "nonfinite_fraction": 0.5}}
    assert divergences(bad) == {
        "5": "standardized_error 7e+04 > 100",
        "50": "non-finite predictions (0.5 of the steps)",
    }


# --------------------------------------------------------------------------- mean bootstrap


def test_two_point_sample_has_the_exact_bootstrap_distribution():
    # resample means of [0, 1] are 0, 0.5, 1 with probabilities 1/4, 1/2, 1/4:
    # the 2.5 % quantile is 0 and the 97.5 % quantile is 1
    assert bootstrap_ci([0.0, 1.0]) == (0.0, 1.0)
    # 50 % interval: quantiles 0.25 and 0.75 of that distribution lie at the edges of the 0.5 atom
    low, high = bootstrap_ci([0.0, 1.0], confidence=0.4)
    assert low == pytest.approx(0.5) and high == pytest.approx(0.5)


def test_three_point_sample_matches_enumerated_bootstrap_distribution():
    x = np.array([1.0, 4.0, 10.0])
    grid = np.array(np.meshgrid(x, x, x)).reshape(3, -1).T  # all 27 equally likely resamples
    exact = np.sort(grid.mean(axis=1))
    low, high = bootstrap_ci(x, confidence=0.8, n_boot=20000, seed=3)
    # the 10 % / 90 % quantiles of the discrete exact distribution (within one atom)
    assert np.quantile(exact, 0.1) - 1.0 <= low <= np.quantile(exact, 0.1) + 1.0
    assert np.quantile(exact, 0.9) - 1.0 <= high <= np.quantile(exact, 0.9) + 1.0
    assert low < x.mean() < high


@pytest.mark.parametrize("n, seed", [(8, 0), (25, 1), (200, 2)])
def test_agrees_with_scipy_percentile_bootstrap(n, seed):
    data = np.random.default_rng(seed).gamma(2.0, 3.0, size=n)  # skewed: the percentile method matters
    ours = bootstrap_ci(data, confidence=0.95, n_boot=20000, seed=seed)
    ref = scipy.stats.bootstrap(
        (data,),
        np.mean,
        confidence_level=0.95,
        n_resamples=20000,
        method="percentile",
        random_state=np.random.default_rng(100 + seed),
    )
    half_width = (ref.confidence_interval.high - ref.confidence_interval.low) / 2
    # two independent Monte-Carlo estimates of the same quantiles: a few % of the half-width apart
    assert ours[0] == pytest.approx(ref.confidence_interval.low, abs=0.05 * half_width)
    assert ours[1] == pytest.approx(ref.confidence_interval.high, abs=0.05 * half_width)


def test_normal_data_gives_the_normal_theory_interval():
    sigma, n = 3.0, 2000
    x = np.random.default_rng(7).normal(5.0, sigma, size=n)
    low, high = bootstrap_ci(x)
    half = 1.96 * sigma / math.sqrt(n)
    assert (low + high) / 2 == pytest.approx(x.mean(), abs=0.05 * half)
    assert (high - low) / 2 == pytest.approx(half, rel=0.06)


def test_ci_is_reproducible_and_equivariant():
    x = np.random.default_rng(0).normal(size=30)
    assert bootstrap_ci(x, seed=5) == bootstrap_ci(x, seed=5)
    assert bootstrap_ci(x, seed=5) != bootstrap_ci(x, seed=6)
    low, high = bootstrap_ci(x, seed=5)
    low2, high2 = bootstrap_ci(2.0 * x + 10.0, seed=5)  # same resamples: affine map of the bounds
    assert low2 == pytest.approx(2 * low + 10) and high2 == pytest.approx(2 * high + 10)
    low3, high3 = bootstrap_ci(x, seed=5, confidence=0.5)
    assert low < low3 < high3 < high


def test_single_value_and_constant_samples_are_degenerate():
    assert bootstrap_ci([3.5]) == (3.5, 3.5)
    assert bootstrap_ci([2.0, 2.0, 2.0]) == (2.0, 2.0)
    s = summarise([4.0])
    assert s == {"mean": 4.0, "ci_low": 4.0, "ci_high": 4.0, "iqm": 4.0, "n": 1}


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 7, 8, 10, 13, 16, 101])
def test_iqm_equals_scipy_trim_mean(n):
    x = np.random.default_rng(n).standard_cauchy(size=n)
    assert iqm(x) == pytest.approx(scipy.stats.trim_mean(x, 0.25), rel=1e-12, abs=1e-12)


def test_iqm_is_the_middle_half_for_multiples_of_four_and_ignores_outliers():
    x = np.array([100.0, -50.0, 1.0, 2.0, 3.0, 4.0, 1e9, -1e9])
    assert iqm(x) == pytest.approx(np.mean([1.0, 2.0, 3.0, 4.0]))
    assert iqm([5.0, 1.0, 3.0]) == pytest.approx(3.0)  # n < 4: nothing cut, the mean
    assert math.isnan(iqm([1.0, float("nan"), 3.0, 4.0]))


def test_summarise_reports_non_finite_values_instead_of_hiding_them():
    s = summarise([1.0, 2.0, float("inf")])
    assert s["mean"] == math.inf and math.isnan(s["ci_low"]) and math.isnan(s["ci_high"]) and s["n"] == 3
    x = [1.0, 2.0, 3.0, 4.0, 5.0]
    s = summarise(x, seed=1)
    assert s["mean"] == 3.0 and s["iqm"] == pytest.approx(3.0) and s["n"] == 5
    assert (s["ci_low"], s["ci_high"]) == bootstrap_ci(x, seed=1)


@pytest.mark.parametrize("bad, match", [([], "empty"), ([[1.0, 2.0], [3.0, 4.0]], "1-D"), ([1.0, float("nan")], "NaN")])
def test_bad_input_raises_value_error(bad, match):
    with pytest.raises(ValueError, match=match):
        bootstrap_ci(bad)


def test_bad_settings_raise_value_error():
    with pytest.raises(ValueError, match="empty"):
        iqm([])
    with pytest.raises(ValueError, match="empty"):
        summarise(np.array([]))
    with pytest.raises(ValueError, match="confidence"):
        bootstrap_ci([1.0, 2.0], confidence=1.0)
    with pytest.raises(ValueError, match="n_boot"):
        bootstrap_ci([1.0, 2.0], n_boot=0)


def test_band_matches_columnwise_ci_and_handles_edge_cases():
    rng = np.random.default_rng(0)
    curves = rng.normal(size=(6, 4)) + np.arange(4)
    low, high = bootstrap_band(curves, n_boot=20000, seed=0)
    for j in range(4):
        ref_low, ref_high = bootstrap_ci(curves[:, j], n_boot=20000, seed=11)
        width = ref_high - ref_low
        assert low[j] == pytest.approx(ref_low, abs=0.06 * width)
        assert high[j] == pytest.approx(ref_high, abs=0.06 * width)
    one_low, one_high = bootstrap_band(curves[:1])
    np.testing.assert_array_equal(one_low, curves[0])
    np.testing.assert_array_equal(one_high, curves[0])
    curves[2, 1] = np.inf
    low, high = bootstrap_band(curves)
    assert np.isnan(low[1]) and np.isnan(high[1]) and np.isfinite(low[[0, 2, 3]]).all()


def test_two_level_iqm_ci_carries_the_data_sets_variance():
    from pets.experiments.statistics import two_level_iqm_ci

    rng = np.random.default_rng(0)
    groups = {d: 1.0 + d + rng.normal(0.0, 0.05, 5) for d in range(3)}  # data sets far apart, seeds close
    point, low, high = two_level_iqm_ci(groups, reps=2000)
    pooled = np.concatenate(list(groups.values()))
    assert point == pytest.approx(scipy.stats.trim_mean(pooled, 0.25), rel=1e-12)
    one_level = iqm_ci(pooled[:, None], reps=2000)  # rliable's stratified bootstrap over the 15 runs as if iid
    assert low <= point <= high
    assert high - low > 1.3 * float(one_level[2][0] - one_level[1][0])  # the outer level widens the interval
    assert two_level_iqm_ci(groups, reps=2000) == (point, low, high)  # seeded
    assert two_level_iqm_ci({0: [2.0, 2.0]}, reps=50) == (2.0, 2.0, 2.0)
    with pytest.raises(ValueError, match="finite"):
        two_level_iqm_ci({0: [1.0, NAN]})


def _two_level_loop(groups, reps, seed, confidence=0.95):
    """The two-level bootstrap as its docstring states it, one replication at a time."""
    from pets.stats.bootstrap import iqm_columns

    samples = [np.asarray(v, dtype=np.float64) for v in groups.values()]
    rng, stats = np.random.default_rng(seed), np.empty(reps)
    for r in range(reps):
        drawn = [samples[g] for g in rng.integers(0, len(samples), size=len(samples))]
        stats[r] = iqm_columns(np.concatenate([x[rng.integers(0, x.size, size=x.size)] for x in drawn])[:, None])[0]
    tail = (1.0 - confidence) / 2.0
    return tuple(float(v) for v in np.quantile(stats, [tail, 1.0 - tail]))


@pytest.mark.parametrize("count, size", [(1, 1), (1, 7), (2, 1), (3, 5), (4, 3), (5, 11)])
def test_two_level_iqm_ci_draws_every_replication_at_once_bit_for_bit(count, size):
    """Equal data set sizes take the vectorised path: the same bounds' draws in one call, the same numbers as the
    replication-by-replication loop, to the last bit, on values spanning six decades; unequal sizes, the loop."""
    from pets.experiments.statistics import two_level_iqm_ci

    for seed in range(5):
        rng = np.random.default_rng(1000 * count + size + seed)
        groups = {d: rng.normal(size=size) * 10 ** rng.uniform(-3, 3) for d in range(count)}
        assert two_level_iqm_ci(groups, reps=3001, seed=seed)[1:] == _two_level_loop(groups, 3001, seed)
    groups = {0: [1.0, 4.0, 2.0], 1: [3.0, 8.0], 2: [0.5]}
    assert two_level_iqm_ci(groups, reps=999, seed=3)[1:] == _two_level_loop(groups, 999, 3)


def test_two_level_iqm_ci_in_blocks_continues_the_stream(monkeypatch):
    """Replications drawn block after block (bounded memory) are the loop's, equal sizes or not."""
    from pets.experiments import statistics

    monkeypatch.setattr(statistics, "_BLOCK_ELEMENTS", 50)  # 3 replications a block for 3 x 5 values
    rng = np.random.default_rng(7)
    for groups in ({d: rng.normal(size=5) for d in range(3)}, {0: rng.normal(size=5), 1: rng.normal(size=2)}):
        assert statistics.two_level_iqm_ci(groups, reps=1001, seed=1)[1:] == _two_level_loop(groups, 1001, 1)
