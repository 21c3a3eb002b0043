"""Mean bootstrap over seeds (the open-loop tables and curves and :mod:`pets.openloop`'s per-episode statistics),
and the IQM of columns that :mod:`pets.experiments.statistics` bootstraps.

:func:`bootstrap_ci` is the percentile bootstrap of the mean (Efron 1979):
``n_boot`` resamples of the ``n`` values with replacement, the ``(1 - c) / 2`` and ``(1 + c) / 2``
quantiles of their means (numpy's linear quantile interpolation), all resamples drawn at once in
blocks; :func:`bootstrap_band` the same pointwise for curves; :func:`summarise` mean, CI, IQM and
n of one sample. With ``n = 1`` the CI is ``(x, x)``; with few values it is too narrow (it cannot see
variation the sample did not show). Non-finite values: :func:`bootstrap_ci` raises ValueError;
:func:`summarise` reports them (mean and IQM as numpy computes them, the CI ``(nan, nan)``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

#: Bootstrap resample means computed per block: keeps the (block, n) index array near 16 MB.
_BLOCK_ELEMENTS = 2_000_000


def _as_sample(values: Any, name: str = "values") -> np.ndarray:
    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"{name} must be a 1-D sequence of numbers, got shape {x.shape}")
    if x.size == 0:
        raise ValueError(f"{name} is empty; a statistic needs at least one value")
    return x


def check_confidence(confidence: float, n_boot: int) -> None:
    """ValueError unless ``confidence`` is in (0, 1) and ``n_boot`` (replications) a positive int."""
    if not (isinstance(confidence, (int, float)) and 0.0 < confidence < 1.0):
        raise ValueError(f"confidence must be a number in (0, 1), got {confidence!r}")
    if isinstance(n_boot, bool) or not isinstance(n_boot, (int, np.integer)) or n_boot < 1:
        raise ValueError(f"n_boot must be a positive int, got {n_boot!r}")


def iqm_columns(scores: np.ndarray) -> np.ndarray:
    """IQM of every column of ``scores`` (runs, columns): ``rliable.metrics.aggregate_iqm`` of each column
    (scipy's ``trim_mean(x, 0.25)``: the same partition and average, vectorised over the columns). A leading
    axis (replications, runs, columns) gives every replication's IQMs, (replications, columns)."""
    n = scores.shape[-2]
    cut = int(0.25 * n)
    return np.partition(scores, (cut, n - cut - 1), axis=-2)[..., cut : n - cut, :].mean(axis=-2)


def bootstrap_means(samples: np.ndarray, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """Means of ``n_boot`` bootstrap resamples of the rows of ``samples`` (n, m): shape (n_boot, m).

    Resample b draws n row indices uniformly with replacement and averages those rows, so every
    column of one resample uses the same rows (the seeds of a curve stay together).
    """
    n, m = samples.shape
    out = np.empty((n_boot, m), dtype=np.float64)
    block = max(1, _BLOCK_ELEMENTS // max(n * m, 1))
    for start in range(0, n_boot, block):
        stop = min(n_boot, start + block)
        idx = rng.integers(0, n, size=(stop - start, n))
        out[start:stop] = samples[idx].mean(axis=1)
    return out


def bootstrap_ci(
    values: Sequence[float] | np.ndarray, *, confidence: float = 0.95, n_boot: int = 10000, seed: int = 0
) -> tuple[float, float]:
    """Percentile-bootstrap ``confidence`` interval of the mean of ``values`` (module docstring).

    ``(low, high)`` are the ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` quantiles of the
    means of ``n_boot`` resamples drawn with ``numpy.random.default_rng(seed)``. ``n = 1`` gives
    ``(x, x)``. ValueError for empty or non-finite input, ``confidence`` outside (0, 1) or
    ``n_boot < 1``.
    """
    x = _as_sample(values)
    check_confidence(confidence, n_boot)
    if not np.isfinite(x).all():
        raise ValueError("values contain NaN or inf; the bootstrap needs finite numbers")
    if x.size == 1 or np.all(x == x[0]):
        return float(x[0]), float(x[0])
    means = bootstrap_means(x[:, None], n_boot, np.random.default_rng(seed))[:, 0]
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(means, [tail, 1.0 - tail])
    return float(low), float(high)


def bootstrap_band(
    curves: np.ndarray, *, confidence: float = 0.95, n_boot: int = 2000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Pointwise percentile-bootstrap CI of the mean curve of ``curves`` (n_seeds, n_points).

    Seeds are resampled as whole curves; returns ``(low, high)``, each (n_points,). Columns with
    non-finite values get NaN bounds; a single seed gives its own curve as both bounds.
    """
    c = np.asarray(curves, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] < 1:
        raise ValueError(f"curves must have shape (n_seeds >= 1, n_points), got {c.shape}")
    check_confidence(confidence, n_boot)
    finite = np.isfinite(c).all(axis=0)
    if c.shape[0] == 1:
        band = np.where(finite, c[0], np.nan)
        return band.copy(), band.copy()
    means = bootstrap_means(np.where(finite, c, 0.0), n_boot, np.random.default_rng(seed))
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(means, [tail, 1.0 - tail], axis=0)
    return np.where(finite, low, np.nan), np.where(finite, high, np.nan)


def iqm(values: Sequence[float] | np.ndarray) -> float:
    """Interquartile mean of one sample (:func:`iqm_columns`). ValueError if empty. NaN if any value is NaN."""
    x = _as_sample(values)
    if np.isnan(x).any():
        return math.nan
    return float(iqm_columns(x[:, None])[0])


def summarise(
    values: Sequence[float] | np.ndarray, *, confidence: float = 0.95, n_boot: int = 10000, seed: int = 0
) -> dict[str, float | int]:
    """``{"mean", "ci_low", "ci_high", "iqm", "n"}`` of ``values`` (CI: :func:`bootstrap_ci`).

    Non-finite values are reported, not dropped: mean/IQM as numpy gives them, CI ``(nan, nan)``.
    ValueError if empty.
    """
    x = _as_sample(values)
    check_confidence(confidence, n_boot)
    if np.isfinite(x).all():
        low, high = bootstrap_ci(x, confidence=confidence, n_boot=n_boot, seed=seed)
    else:
        low = high = math.nan
    with np.errstate(invalid="ignore"):
        mean = float(x.mean())
    return {"mean": mean, "ci_low": low, "ci_high": high, "iqm": iqm(x), "n": int(x.size)}
