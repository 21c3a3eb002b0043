"""Statistics over seeds: the A/B statistics of both comparisons (rliable); the mean bootstrap of the open-loop
statistics is :mod:`pets.stats.bootstrap`.

**A/B statistics** (:mod:`pets.experiments.offline_summary` and :mod:`pets.experiments.studies.online`),
a thin layer over rliable (Agarwal et al. 2021, "Deep RL at the edge of the statistical precipice"):

- :func:`iqm_ci`: per column of a (runs, columns) score matrix the interquartile mean (IQM, rliable's
  ``metrics.aggregate_iqm`` = ``scipy.stats.trim_mean(x, 0.25)``: sort, drop ``floor(n / 4)`` values
  at each end, average the rest; for ``n < 4`` the plain mean) with its 95 % stratified-bootstrap
  percentile CI, rliable's ``library.get_interval_estimates`` for all columns at once. The stratified
  bootstrap resamples the runs of every column independently, so a column's interval is the
  percentile bootstrap of that column alone, whatever else is in the call.
- :func:`p_improvement` / :func:`p_improvement_ci`: the probability that a model is better than the
  baseline, ``P(X better than Y) + P(X = Y) / 2`` for a random run X of the model and Y of the
  baseline (rliable's ``metrics.probability_of_improvement``: on the negated values for errors,
  where lower is better; on the values themselves with ``higher_is_better=True``, e.g. rewards), with
  the CI of rliable's independent stratified bootstrap (each model's runs resampled on their own).
  Diverged runs (non-finite values) enter as the worst value (error ``+inf``, reward ``-inf``):
  rank-based, a diverged run loses to every finite run and ties (counts half) with another diverged one.
- :func:`iqm_ci_finite`: :func:`iqm_ci` per column over the finite values only, for score matrices
  where a run is left out of some columns (diverged at one horizon) and counts in the others.
- :func:`paired_ratios` / :func:`paired_differences`: per seed that both have (both not diverged) the
  ratio model / baseline (errors: same data, same start points) or the difference model - baseline
  (rewards, which can be negative: same seed, same env seeds); :func:`iqm_ci` of those is the paired
  effect with its CI.
- :func:`sign_flip_p`: the exact paired permutation (sign-flip) p-value of a mean paired difference, beside the
  bootstrap CIs (which are too narrow at n = 5: a percentile CI can exclude 0 where no exact test can reject);
  :func:`holm`: Holm's adjustment of a family of p-values (the primary endpoint over envs and arms);
  :func:`two_level_iqm_ci`: the IQM's CI with data sets as the outer level of a two-level bootstrap.
- :func:`divergence` / :func:`divergences`: per horizon, whether a run's evaluation holds a non-finite
  value there, or predictions that went non-finite, or a ``standardized_error`` at or past the env's
  no-information level (:mod:`pets.experiments.studies.primary`; :data:`DIVERGED_STANDARDIZED_ERROR` without one).
  A run diverged at a horizon is counted and shown as such there,
  never averaged into an IQM; at its other horizons it counts normally.

Small samples: the IQM of ``n <= 3`` values is their mean, and the percentile bootstrap of a mean
of ``n <= 3`` values is exactly ``[min, max]`` of the values (all-min and all-max resamples have
probability ``n**-n >= 1/27 > 2.5 %``): with 3 seeds, non-overlapping CIs only say "3 of 3 seeds
ordered". Fewer than 5 seeds cannot carry a claim.

Reproducibility: rliable's bootstraps draw their indices from numpy's *global* generator
(``np.random.choice``) and ignore their ``random_state`` argument; every call here seeds the global
generator with ``seed`` and restores its previous state afterwards, so the same inputs give the
same numbers in every process, whatever ran before.

Speed: the intervals are :func:`pets.stats.stratified.stratified_percentile_ci`, rliable's stratified percentile
bootstrap with all replications drawn and evaluated at once: the same numbers bit for bit and the same draws from
the global generator (the tests pin both against rliable itself), without arch's loop of one Python iteration per
replication (``docs/scripts/bench_bootstrap.py`` prints both costs; docs/performance.md). The statistics
bootstrapped are :func:`iqm_columns`, the partition-and-average of ``scipy.stats.trim_mean`` vectorised over
columns and replications (bit-identical to ``aggregate_iqm`` per column; the tests pin it), and
:func:`p_lower_columns` for the probability of improvement (identical to ``probability_of_improvement`` per
column). :data:`REPS` replications: see its comment.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from pets.stats.bootstrap import check_confidence, iqm_columns
from pets.stats.stratified import stratified_percentile_ci

#: The model every other model (arm) of a comparison is compared with: P of improvement, ratios, differences.
BASELINE = "delta"
#: Seeds a comparison needs before it can carry a claim (``pets.compare`` warns below it).
MIN_SEEDS = 5
#: What a report says under a statistic of fewer than :data:`MIN_SEEDS` seeds.
SMALL_SAMPLE_NOTE = (
    f"Fewer than {MIN_SEEDS} seeds cannot carry a claim: with n <= 3 the IQM is the mean and its 95 % "
    "percentile-bootstrap CI is exactly [min, max] of the seeds."
)
#: Confidence level of every interval.
CONFIDENCE = 0.95
#: Family-wise error rate of every verdict (Holm's adjusted p below it: a win or a loss).
ALPHA = 0.05
#: Bootstrap replications of the rliable intervals. The percentile CI of an IQM over 5 seeds has at
#: most C(9, 5) = 126 distinct resample values per column, and 5000 replications put the 2.5 %
#: quantile within about 0.5 percentage points of probability.
REPS = 5_000
#: Bootstrap indices drawn per block of replications in :func:`two_level_iqm_ci` (about 16 MB of int64).
_BLOCK_ELEMENTS = 2_000_000
#: A run whose ``standardized_error`` (the RMS prediction error in units of the training data's standard
#: deviations) exceeds this at a horizon is diverged at that horizon: predicting the data mean scores about 1 and an
#: independent draw from the data about 1.4, so 100 is far beyond any model that still tracks the state.
DIVERGED_STANDARDIZED_ERROR = 100.0


# --------------------------------------------------------------------------- A/B statistics (rliable)
@contextmanager
def _global_numpy_seed(seed: int) -> Iterator[None]:
    """Seed numpy's global generator (what rliable draws from) for the block; restore its state after."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def _check_reps(reps: int) -> None:
    if isinstance(reps, bool) or not isinstance(reps, (int, np.integer)) or reps < 1:
        raise ValueError(f"reps must be a positive int, got {reps!r}")


def _score_matrix(scores: Any, name: str) -> np.ndarray:
    x = np.asarray(scores, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"{name} must have shape (runs >= 1, columns >= 1), got {x.shape}")
    return x


def iqm_ci(
    scores: Any, *, reps: int = REPS, seed: int = 0, confidence: float = CONFIDENCE
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(iqm, ci_low, ci_high)``, each (columns,): per column of ``scores`` (runs, columns) the IQM and its
    stratified-bootstrap percentile CI (rliable's ``library.get_interval_estimates``, ``reps`` replications,
    numpy's global generator seeded with ``seed`` for the call; computed by
    :func:`~pets.stats.stratified.stratified_percentile_ci`). One run gives ``(x, x, x)``.

    ValueError for non-finite scores (diverged runs are left out by the caller, never averaged in), an
    empty matrix or ``reps < 1``.
    """
    x = _score_matrix(scores, "scores")
    _check_reps(reps)
    check_confidence(confidence, reps)
    if not np.isfinite(x).all():
        raise ValueError("scores contain NaN or inf; leave diverged runs out before the IQM")
    with _global_numpy_seed(seed):
        return stratified_percentile_ci([x], iqm_columns, reps=reps, confidence=confidence)


def iqm_ci_finite(
    scores: Any, *, reps: int = REPS, seed: int = 0, confidence: float = CONFIDENCE
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`iqm_ci` of every column of ``scores`` (runs, columns) over its finite values only: a NaN or inf
    is a run left out of that column (e.g. diverged at that horizon). NaN where a column has no finite value.

    Columns with the same finite runs share one :func:`iqm_ci` call, so with every value finite this is
    exactly :func:`iqm_ci` (one call, the same numbers)."""
    x = _score_matrix(scores, "scores")
    finite = np.isfinite(x)
    groups: dict[bytes, list[int]] = {}
    for j in np.flatnonzero(finite.any(axis=0)):
        groups.setdefault(finite[:, j].tobytes(), []).append(int(j))
    out = np.full((3, x.shape[1]), np.nan)
    for cols in groups.values():
        rows = finite[:, cols[0]]
        out[:, cols] = iqm_ci(x[np.ix_(rows, cols)], reps=reps, seed=seed, confidence=confidence)
    return out[0], out[1], out[2]


def _as_errors(values: Any, name: str, higher_is_better: bool = False) -> np.ndarray:
    """Values as a float error matrix (runs, columns), lower is better: negated if ``higher_is_better``;
    every non-finite value (a diverged run) set to +inf, the worst."""
    x = np.asarray(values, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    x = _score_matrix(x, name)
    if higher_is_better:
        x = -x
    return np.where(np.isfinite(x), x, np.inf)


def p_lower_columns(err_x: np.ndarray, err_y: np.ndarray) -> np.ndarray:
    """Per column ``P(X < Y) + P(X = Y) / 2`` over all pairs of a run of ``err_x`` and one of ``err_y``:
    ``rliable.metrics.probability_of_improvement(-err_x, -err_y)`` of each column, vectorised. A leading
    axis (replications, runs, columns) on both gives every replication's, (replications, columns)."""
    a, b = err_x[..., :, None, :], err_y[..., None, :, :]
    wins = (a < b).sum(axis=(-3, -2)) + 0.5 * (a == b).sum(axis=(-3, -2))
    return wins / (err_x.shape[-2] * err_y.shape[-2])


def p_improvement(model: Any, baseline: Any, *, higher_is_better: bool = False) -> float:
    """Probability that the model is better than the baseline: ``P(X < Y) + P(X = Y) / 2`` for a random run
    X of the model and Y of the baseline (1-D per-run values of one quantity), errors by default, or
    ``P(X > Y) + P(X = Y) / 2`` with ``higher_is_better`` (rewards).

    rliable's ``metrics.probability_of_improvement`` (the Mann-Whitney U statistic over ``n_x n_y``) on
    the negated errors, or on the values themselves with ``higher_is_better``. NaN and inf (diverged
    runs) count as the worst value (error ``+inf``, reward ``-inf``): a diverged run loses every
    comparison with a finite one and ties (half) with another diverged one; rank-based, so no size of a
    finite value changes the result more than its rank does.
    """
    from rliable import metrics

    x = _as_errors(model, "model", higher_is_better)
    y = _as_errors(baseline, "baseline", higher_is_better)
    if x.shape[1] != 1 or y.shape[1] != 1:
        raise ValueError("p_improvement compares 1-D per-run values; use p_improvement_ci for columns")
    return float(metrics.probability_of_improvement(-x, -y))


def p_improvement_ci(
    model: Any,
    baseline: Any,
    *,
    higher_is_better: bool = False,
    reps: int = REPS,
    seed: int = 0,
    confidence: float = CONFIDENCE,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(p, ci_low, ci_high)``, each (columns,): :func:`p_improvement` of every column of ``model``
    (runs_model, columns) against ``baseline`` (runs_baseline, columns) with rliable's stratified
    independent bootstrap CI (each model's runs resampled on their own; ``reps`` replications, seed as
    :func:`iqm_ci`). 1-D inputs are one column. Non-finite values count as the worst (diverged)."""
    x = _as_errors(model, "model", higher_is_better)
    y = _as_errors(baseline, "baseline", higher_is_better)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"model and baseline need the same columns, got {x.shape} and {y.shape}")
    _check_reps(reps)
    check_confidence(confidence, reps)
    with _global_numpy_seed(seed):
        return stratified_percentile_ci([x, y], p_lower_columns, reps=reps, confidence=confidence)


def paired_ratios(model: Mapping[Any, Any], delta: Mapping[Any, Any]) -> tuple[list[Any], np.ndarray]:
    """``(seeds, ratios)``: per seed in both ``model`` and ``delta`` ({seed: per-column errors}, NaN where the
    run diverged) the ratio model / delta, shape (seeds, columns); seeds in sorted order.

    Pairing by seed compares runs trained with the same seed on the same data and evaluated from the
    same start points. A ratio is NaN where either error is not finite (that pair is left out of that
    column: :func:`iqm_ci_finite`). A column whose ratio is not finite for some seed where both errors
    are (delta's error 0, e.g. a part the env does not have) is NaN for every seed.
    """
    seeds = sorted(set(model) & set(delta))
    if not seeds:
        return [], np.empty((0, 0))
    num = np.array([np.asarray(model[s], dtype=np.float64) for s in seeds])
    den = np.array([np.asarray(delta[s], dtype=np.float64) for s in seeds])
    both = np.isfinite(num) & np.isfinite(den)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = np.where(both, num / den, np.nan)
    defined = (np.isfinite(ratios) | ~both).all(axis=0)
    return seeds, np.where(defined, ratios, np.nan)


def paired_differences(model: Mapping[Any, Any], baseline: Mapping[Any, Any]) -> tuple[list[Any], np.ndarray]:
    """``(seeds, differences)``: per seed in both ``model`` and ``baseline`` ({seed: value or per-column
    values} of the runs that did not diverge) the difference model - baseline, shape (seeds, columns);
    seeds in sorted order. For rewards (which can be negative, so no ratio): the same seed of two online
    arms collects the same random seed data and resets its trials with the same env seeds."""
    seeds = sorted(set(model) & set(baseline))
    if not seeds:
        return [], np.empty((0, 0))
    a = np.array([np.atleast_1d(np.asarray(model[s], dtype=np.float64)) for s in seeds])
    b = np.array([np.atleast_1d(np.asarray(baseline[s], dtype=np.float64)) for s in seeds])
    return seeds, a - b


#: Pairs up to which :func:`sign_flip_p` enumerates every sign pattern (2^16 = 65,536 patterns); above, it samples.
EXACT_SIGN_FLIP_MAX_PAIRS = 16
#: Random sign patterns of the Monte Carlo p-value above :data:`EXACT_SIGN_FLIP_MAX_PAIRS` pairs.
SIGN_FLIP_DRAWS = 100_000


def sign_flip_p(differences: Any, *, seed: int = 0) -> float:
    """Two-sided paired permutation (sign-flip) p-value of the mean of paired ``differences``.

    Under the null (the two arms' outcomes exchangeable within a pair) each difference's sign is a fair coin, so
    the p-value is the fraction of the ``2^n`` sign patterns whose mean is at least as far from 0 as the
    observed one (``|mean(s * d)| >= |mean(d)|``, with a relative tolerance of 1e-9 for float ties): exact up to
    :data:`EXACT_SIGN_FLIP_MAX_PAIRS` pairs (the smallest attainable value is ``2 / 2^n``: 0.0625 at n = 5, so
    five pairs can never reach p < 0.05); above, ``(1 + hits) / (1 + draws)`` over :data:`SIGN_FLIP_DRAWS`
    random patterns drawn with ``seed`` (the unbiased Monte Carlo permutation p-value). Differences must be
    finite (a diverged run enters as the worst outcome, decided by the caller); an empty sample gives NaN.
    """
    d = np.asarray(differences, dtype=np.float64).reshape(-1)
    if not np.isfinite(d).all():
        raise ValueError("sign_flip_p needs finite differences (enter a diverged run as the worst outcome)")
    n = d.size
    if n == 0:
        return math.nan
    observed = abs(d.mean()) * (1 - 1e-9) - 1e-300
    if n > EXACT_SIGN_FLIP_MAX_PAIRS:
        signs = np.random.default_rng(seed).choice(np.array([-1.0, 1.0]), size=(SIGN_FLIP_DRAWS, n))
        hits = int((np.abs(signs @ d / n) >= observed).sum())
        return (1 + hits) / (1 + SIGN_FLIP_DRAWS)
    bits = (np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1  # every sign pattern, one row each
    means = np.abs(((1 - 2 * bits) * d).mean(axis=1))
    return float(np.mean(means >= observed))


def two_level_iqm_ci(
    groups: Mapping[Any, Sequence[float]], *, reps: int = REPS, seed: int = 0, confidence: float = CONFIDENCE
) -> tuple[float, float, float]:
    """``(iqm, ci_low, ci_high)`` of values grouped by data set ({data set: values over model seeds}): the IQM of
    all values, with the percentile CI of a two-level bootstrap: each replication draws the data sets with
    replacement (outer level), then within each drawn data set its values with replacement (inner level), and
    takes the IQM of the pooled draw. A claim that rests on the data then carries the data sets' variance too,
    not only that of network initialisation. One data set: the one-level bootstrap of its values.

    Replication ``r`` draws from ``numpy.random.default_rng(seed)`` the data sets (``integers(0, G, size=G)``),
    then each drawn one's indices (``integers(0, n_g, size=n_g)``), replication after replication. Where every
    data set has the same number of values, the draws' bounds do not depend on what was drawn, and one
    ``integers`` call over the bounds laid out in that order draws the same numbers (numpy's bounded integers
    take one element at a time from the generator's stream, whether the bound is a scalar or an array;
    tests/test_stats.py pins it against the loop), so every replication is drawn at once; otherwise each one's
    inner indices are drawn in one call. Either way the IQMs of replications of one pooled size are computed
    together."""
    _check_reps(reps)
    check_confidence(confidence, reps)
    samples = [np.asarray(v, dtype=np.float64).reshape(-1) for v in groups.values()]
    if not samples or any(x.size == 0 or not np.isfinite(x).all() for x in samples):
        raise ValueError("two_level_iqm_ci needs finite values in every group and at least one group")
    rng = np.random.default_rng(seed)
    count, sizes = len(samples), np.array([x.size for x in samples])
    values, starts = np.concatenate(samples), np.cumsum(sizes) - sizes
    stats = np.empty(reps)
    block = max(1, _BLOCK_ELEMENTS // (count + count * int(sizes.max())))  # blocks continue the stream
    for start in range(0, reps, block):
        rows = min(block, reps - start)
        if (sizes == sizes[0]).all():
            size = int(sizes[0])
            bounds = np.concatenate([np.full(count, count), np.full(count * size, size)])
            draws = rng.integers(0, np.broadcast_to(bounds, (rows, bounds.size)))
            picks = list(starts[draws[:, :count], None] + draws[:, count:].reshape(rows, count, size))
        else:  # the bounds depend on the data sets drawn: two calls a replication
            picks = []
            for _ in range(rows):
                outer = rng.integers(0, count, size=count)
                drawn = sizes[outer]
                picks.append(np.repeat(starts[outer], drawn) + rng.integers(0, np.repeat(drawn, drawn)))
        stats[start : start + rows] = _pooled_iqms(values, [p.reshape(-1) for p in picks])
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(stats, [tail, 1.0 - tail])
    return float(iqm_columns(values[:, None])[0]), float(low), float(high)


def _pooled_iqms(values: np.ndarray, picks: Sequence[np.ndarray]) -> np.ndarray:
    """The IQM of ``values[p]`` for every replication's indices ``p``; those of one pooled size at once."""
    stats, lengths = np.empty(len(picks)), np.array([p.size for p in picks])
    for length in np.unique(lengths):
        rows = np.flatnonzero(lengths == length)
        stats[rows] = iqm_columns(values[np.stack([picks[r] for r in rows]), None])[:, 0]
    return stats


def ci_exact_note(low: float | None, high: float | None, null: float, p: float | None, alpha: float = 0.05) -> str:
    """Where the bootstrap CI and the exact test disagree at ``alpha``: the CI excludes ``null`` while the exact p is
    at least ``alpha``, or the CI contains it while p is below; "" where they agree or a value is missing.

    Percentile-bootstrap CIs of few pairs are narrower than the exact test (5 pairs all one way: the CI excludes the
    null, but p cannot go below 0.0625); the exact p is the one that carries a claim.
    """
    if any(v is None or not math.isfinite(v) for v in (low, high, p)):
        return ""
    excludes = low > null or high < null
    if excludes and p >= alpha:
        return f"the bootstrap CI excludes {null:g}, the exact p is {p:.3g}: not significant at {alpha:g}"
    if not excludes and p < alpha:
        return f"the exact p is {p:.3g} but the bootstrap CI contains {null:g}"
    return ""


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (family-wise error over the family given), in the input order.

    Sorted ascending, the i-th smallest (0-based) is multiplied by ``m - i``, made non-decreasing, capped at 1.
    NaN entries (no test) stay NaN and are not counted in ``m``.
    """
    p = np.asarray(p_values, dtype=np.float64).reshape(-1)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    if ok.size:
        order = ok[np.argsort(p[ok], kind="stable")]
        scaled = p[order] * (ok.size - np.arange(ok.size))
        out[order] = np.minimum(np.maximum.accumulate(scaled), 1.0)
    return out.tolist()


def divergence(values: Mapping[str, Any], level: float | None = None) -> str | None:
    """Why a run diverged at one horizon, or None if it did not, from its evaluation's ``{key: value}`` at that
    horizon: a value is not finite, ``nonfinite_fraction > 0`` (some predictions went inf/NaN) or
    ``standardized_error`` (when the key exists) at or past ``level``, the env's no-information level
    (:mod:`pets.experiments.studies.primary`); without a level, past :data:`DIVERGED_STANDARDIZED_ERROR`."""
    for key, value in values.items():
        v = float(value)
        if not math.isfinite(v):
            return f"{key} {v}"
        if key == "nonfinite_fraction" and v > 0:
            return f"non-finite predictions ({v:.3g} of the steps)"
        if key == "standardized_error":
            if level is not None and v >= level:
                return f"standardized_error {v:.3g} >= the no-information level {level:.3g}"
            if level is None and v > DIVERGED_STANDARDIZED_ERROR:
                return f"standardized_error {v:.3g} > {DIVERGED_STANDARDIZED_ERROR:g}"
    return None


def divergences(horizons: Mapping[str, Mapping[str, Any]], level: float | None = None) -> dict[str, str]:
    """``{horizon: why}`` of every horizon at which a run diverged (:func:`divergence` with ``level``), from its
    evaluation's ``{"horizon": {key: value}}``; empty if it diverged at none. At the other horizons it counts."""
    return {h: why for h, values in horizons.items() if (why := divergence(values, level)) is not None}
