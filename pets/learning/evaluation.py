"""Long-horizon prediction error of a trained model on recorded trajectories (the paper's offline evaluation).

The command ``python -m pets.evaluate`` is :mod:`pets.tools.evaluate`.

Protocol (GEM paper, section "Long horizon prediction"): pick K random start points (episode i, step t)
that leave room for the largest horizon H (``t + H <= lengths[i]``; horizons longer than every episode
are skipped with a message). From the true observation ``obs[i, t]`` roll the model forward with the
recorded actions ``act[i, t:t + H]``; compare the predicted ``s_k`` with the true ``obs[i, t + k]``.
All K starts are rolled out together (one batched rollout), and every horizon uses the same starts.

- ``mean`` (default): deterministic; the next target is the mean of the elite members' predicted means,
  mapped through ``head.next_obs``.
- ``sample``: TS-inf with one particle per start: each start keeps one elite member (uniform draw) for
  the whole rollout and samples ``target = mean + exp(logvar / 2) eps`` every step.

Both modes work with every ``--model``. For the deterministic models (delta-det, gem2) ``mean`` is the paper's
averaged ensemble and ``sample`` follows one member per start without noise (their log-variance makes
``exp(logvar / 2)`` exactly 0, see :mod:`pets.models`).

Step-wise errors (:func:`step_errors`, the same for every head) of a prediction ``x`` of the observation ``x'``:

- ``e`` (the paper's): Euclidean over all entries with the differences taken on the groups, as since
  the first version: ``SO2_angle`` ``wrap(a - a')`` (to (-pi, pi]), ``SO3_quat`` up to sign
  ``min(|q - q'|, |q + q'|)`` (not normalised), everything else (``SO2_cossin``, derived entries too) plain.
- ``translation``, ``velocity``, ``other``, ``derived``: ``|x - x'|`` over the Rn group coordinates,
  ``layout.velocities``, ``layout.other``, ``layout.derived`` (the MuJoCo quantities a model carries over).
- ``rotation``: ``sqrt(sum_g theta_g^2)`` over the rotation groups g of the geodesic angles (radians)
  ``theta = |wrap(a - a')|`` (SO2_angle; SO2_cossin with ``a = atan2(sin, cos)``) and
  ``theta = 2 acos|<q/|q|, q'/|q'|>|`` (SO3_quat, computed as ``4 atan2(|q - s q'|, |q + s q'|)``,
  ``s = sign <q, q'>``); 0 without rotation groups.
- ``standardized``: ``sqrt(mean_i (d_i / sigma_i)^2)`` over the predicted (non-derived) entries i, ``d_i``
  the per-entry difference (wrapped for SO2_angle; normalised, sign-aligned quaternions for SO3_quat; plain
  else), ``sigma_i`` the std of entry i over the training observations (``--train-data``, default the test
  data itself; ``sigma_i < 1e-8`` counts as 1): no block dominates by its units; 0 is perfect, about 1.4
  (sqrt 2) a prediction no better than an independent draw from the data.

Per horizon h: ``mean_step_error`` = mean over starts and over k = 1..h of ``e_k`` (the paper's average
step-wise error), ``final_step_error`` = mean over starts of ``e_h``; ``translation_error``,
``rotation_error``, ``velocity_error``, ``other_error``, ``derived_error``, ``standardized_error`` = the same
average as ``mean_step_error`` of each (so is a metric of one's own: :func:`register_metric`,
:mod:`pets.learning.error_metrics`); ``nonfinite_fraction``: the share of (start, step) pairs whose
prediction is not finite (a diverging model: those make the averages inf/NaN, reported as such, never hidden).
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pets.data.datasets import env_name, load_dataset
from pets.learning.error_metrics import (  # noqa: F401 (register_metric: a metric of one's own)
    HORIZON_KEYS,
    METRICS,
    PARTS,
    own_step_errors,
    register_metric,
)

if TYPE_CHECKING:
    from torch import Tensor

    from envs.layout import ObsLayout

PROG = "pets.evaluate"
DEFAULT_HORIZONS = (1, 5, 10, 25, 50)
DEFAULT_STARTS = 1000
MODES = ("mean", "sample")
# PARTS, METRICS (the built-in ones) and HORIZON_KEYS: pets.learning.error_metrics (a registered metric's key comes
# after the built-in metrics, before nonfinite_fraction)
#: Standard deviations below this count as 1 in ``standardized_error`` (constant entries of the training data).
MIN_STD = 1e-8


# --------------------------------------------------------------------------- metric
def wrap_angle(d: Tensor) -> Tensor:
    """Angle difference wrapped to (-pi, pi]: :func:`gem_head.lie.wrap_angle`, the wrap of the GEM head's targets."""
    from gem_head.lie import wrap_angle

    return wrap_angle(d)


def layout_parts(layout: ObsLayout) -> dict[str, tuple[int, ...]]:
    """The observation indices of each part of :data:`PARTS`: ``translation`` (Rn group coordinates),
    ``rotation`` (the entries of the groups whose codec is a rotation: SO2_angle, SO2_cossin, SO3_quat),
    ``velocity``, ``other`` and ``derived`` (the layout's lists). Every index is in exactly one part, as a layout
    covers each index once."""
    from gem_head.codecs import CODECS

    return {
        "translation": tuple(i for g in layout.groups if not CODECS[g.kind].is_rotation for i in g.indices),
        "rotation": tuple(i for g in layout.groups if CODECS[g.kind].is_rotation for i in g.indices),
        "velocity": tuple(layout.velocities),
        "other": tuple(layout.other),
        "derived": tuple(layout.derived),
    }


def _check_shapes(pred: Tensor, true: Tensor, layout: ObsLayout) -> None:
    if pred.shape != true.shape or pred.shape[-1] != layout.obs_dim:
        raise ValueError(
            f"pred and true must have the same shape (..., obs_dim={layout.obs_dim}), "
            f"got {tuple(pred.shape)} and {tuple(true.shape)}"
        )


def _total_squared(pred: Tensor, true: Tensor, layout: ObsLayout) -> Tensor:
    """``e^2`` of the paper's step error: each group's codec's ``step_terms`` (``gem_head.codecs``: Rn and
    SO2_cossin ``|x - x'|^2``, SO2_angle ``wrap(x - x')^2``, SO3_quat as given ``min(|q - q'|^2, |q + q'|^2)``),
    summed by the codecs' ``step_place`` in increasing order, then velocities, other and derived ``|x - x'|^2``.
    The summation order is the metric's since the first version of this module (do not change: ``mean_step_error``
    of old and new evaluations must agree bit for bit)."""
    import torch

    from gem_head.codecs import CODECS

    places: dict[int, list[Tensor]] = {}
    for g in layout.groups:
        codec, ix = CODECS[g.kind], list(g.indices)
        places.setdefault(codec.step_place, []).append(codec.step_terms(pred[..., ix], true[..., ix]))
    total = pred.new_zeros(pred.shape[:-1])
    for place in sorted(places):
        total = total + torch.cat(places[place], dim=-1).sum(-1)

    def sq(ix: Sequence[int]) -> Tensor:
        if not ix:
            return pred.new_zeros(pred.shape[:-1])
        i = torch.tensor(list(ix), dtype=torch.long, device=pred.device)
        return (pred.index_select(-1, i) - true.index_select(-1, i)).pow(2).sum(-1)

    return total + sq(layout.velocities) + sq(layout.other + layout.derived)


def rotation_angles(pred: Tensor, true: Tensor, layout: ObsLayout) -> Tensor:
    """Geodesic angle in [0, pi] between predicted and true orientation, one per rotation group of the layout
    (in layout order): ``(..., n_rotation_groups)`` for ``(..., obs_dim)`` inputs, each its codec's
    ``rotation_angle`` (gem_head.codecs: SO2_angle ``|wrap(a - a')|``; SO2_cossin the same with ``a = atan2(sin,
    cos)``; SO3_quat ``2 acos |<q, q'>|`` of the normalised quaternions, exact near 0).
    A group with a non-finite entry gives NaN (atan2 would turn an infinity into a finite angle).
    """
    import torch

    from gem_head.codecs import CODECS

    _check_shapes(pred, true, layout)
    angles = []
    for g in layout.groups:
        ix, codec = list(g.indices), CODECS[g.kind]
        if not codec.is_rotation:
            continue
        angle = codec.rotation_angle(pred[..., ix], true[..., ix])
        finite = torch.isfinite(pred[..., ix]).all(-1) & torch.isfinite(true[..., ix]).all(-1)
        angles.append(torch.where(finite, angle, torch.full_like(angle, float("nan"))))
    return torch.stack(angles, dim=-1) if angles else pred.new_zeros((*pred.shape[:-1], 0))


def entry_differences(pred: Tensor, true: Tensor, layout: ObsLayout) -> Tensor:
    """Group-aware per-entry differences ``d = pred - true`` ``(..., obs_dim)``, each group's its codec's
    ``entry_difference`` (wrapped to (-pi, pi] for SO2_angle; for SO3_quat ``s q/|q| - q'/|q'|`` with
    ``s = sign <q, q'>``; plain elsewhere, SO2_cossin too)."""
    from gem_head.codecs import CODECS

    _check_shapes(pred, true, layout)
    d = pred - true
    for g in layout.groups:  # each kind's own difference (its codec's)
        ix = list(g.indices)
        d[..., ix] = CODECS[g.kind].entry_difference(pred[..., ix], true[..., ix])
    return d


def step_errors(
    pred: Tensor, true: Tensor, layout: ObsLayout, obs_std: Tensor | np.ndarray | None = None
) -> dict[str, Tensor]:
    """The step-wise errors of predictions ``pred`` of observations ``true``, each of shape ``(...)`` for
    ``(..., obs_dim)`` inputs (see the module docstring for the formulas):

    - ``total``: the paper's Euclidean step error (:func:`_total_squared`);
    - ``translation``, ``velocity``, ``other``, ``derived``: ``|x - x'|`` over that part's entries
      (:func:`layout_parts`); ``rotation``: ``sqrt(sum of squared rotation_angles)``, 0 without rotation groups;
    - ``standardized`` (only with ``obs_std``, the per-entry std of the training observations, shape (obs_dim,)):
      ``sqrt(mean_i (d_i / sigma_i)^2)`` over the predicted (non-derived) entries, d from
      :func:`entry_differences`, ``sigma_i = obs_std[i]`` (1 where it is below :data:`MIN_STD`).

    Non-finite predictions give non-finite errors (inf or NaN), never a finite number.
    """
    import torch

    _check_shapes(pred, true, layout)
    diff = pred - true
    parts = layout_parts(layout)
    errors = {"total": _total_squared(pred, true, layout).sqrt()}
    for part in PARTS:
        if part == "rotation":
            errors[part] = rotation_angles(pred, true, layout).norm(dim=-1)
        else:
            errors[part] = diff[..., list(parts[part])].norm(dim=-1)
    if obs_std is not None:
        sigma = torch.as_tensor(obs_std, dtype=pred.dtype, device=pred.device)
        if sigma.shape != (layout.obs_dim,):
            raise ValueError(f"obs_std must have shape ({layout.obs_dim},), got {tuple(sigma.shape)}")
        sigma = torch.where(sigma < MIN_STD, torch.ones_like(sigma), sigma)
        ix = list(layout.predicted_indices)
        z = entry_differences(pred, true, layout)[..., ix] / sigma[ix]
        errors["standardized"] = z.pow(2).mean(-1).sqrt()
    return errors


def obs_std(arrays: Mapping[str, np.ndarray]) -> np.ndarray:
    """Per-entry standard deviation (obs_dim,) of the real (un-padded) observations of a data set
    (:mod:`pets.data.datasets`): ``obs[i, :lengths[i] + 1]`` of every episode i."""
    obs, lengths = np.asarray(arrays["obs"], dtype=np.float64), np.asarray(arrays["lengths"])
    real = np.arange(obs.shape[1])[None, :] <= lengths[:, None]  # (n, T + 1): reset observation and every step
    return obs[real].std(axis=0)


# --------------------------------------------------------------------------- rollout
def parse_horizons(text: str) -> list[int]:
    """``"1,5,10"`` -> ``[1, 5, 10]`` (sorted, unique); ValueError unless all are positive ints."""
    message = f"--horizons must be comma-separated positive ints such as 1,5,10,25,50, got {text!r}"
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(message) from None
    if not values or min(values) < 1:
        raise ValueError(message)
    return sorted(set(values))


def sample_starts(lengths: np.ndarray, horizon: int, starts: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``starts`` distinct (episode, t) pairs with ``t + horizon <= lengths[episode]``, shape (K, 2),
    drawn uniformly without replacement (all of them, in order, if there are no more than ``starts``)."""
    lengths = np.asarray(lengths)
    room = np.maximum(lengths - horizon + 1, 0)  # valid t per episode: 0 .. lengths - horizon
    ep = np.repeat(np.arange(len(lengths)), room)
    t = np.concatenate([np.arange(r) for r in room]) if room.sum() else np.zeros(0, np.int64)
    pairs = np.stack([ep, t], axis=1).astype(np.int64)
    if len(pairs) > starts:
        pairs = pairs[np.sort(rng.choice(len(pairs), size=starts, replace=False))]
    return pairs


def load_inputs(
    run_dir: str | Path,
    data: str | Path | Mapping[str, np.ndarray],
    horizons: Sequence[int],
    starts: int,
    mode: str,
    device: str = "auto",
    train_data: str | Path | Mapping[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Validate the arguments of :func:`evaluate` and load the model and data (ValueError / ConfigError if bad)."""
    from pets.config import load_run_config

    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    if isinstance(starts, bool) or not isinstance(starts, int) or starts < 1:
        raise ValueError(f"starts must be a positive int, got {starts!r}")
    horizons = sorted({int(h) for h in horizons})
    if not horizons or horizons[0] < 1:
        raise ValueError(f"horizons must be positive ints, got {horizons}")
    arrays = load_dataset(data) if isinstance(data, (str, Path)) else data
    longest = int(np.asarray(arrays["lengths"]).max())
    if min(horizons) > longest:
        raise ValueError(f"every horizon is longer than the longest episode ({longest} steps); use shorter horizons")
    run_env = str(load_run_config(run_dir).env)  # env check before the model is built
    if env_name(arrays) != run_env:
        raise ValueError(f"the data set is from {env_name(arrays)} but run {run_dir} models {run_env}")
    if train_data is None:
        train_arrays, standardized_by = arrays, "test data"
    elif isinstance(train_data, (str, Path)):
        train_arrays, standardized_by = load_dataset(train_data), str(train_data)
    else:
        train_arrays, standardized_by = train_data, "arrays"
    if env_name(train_arrays) != run_env:
        raise ValueError(f"the training data set is from {env_name(train_arrays)} but run {run_dir} models {run_env}")
    from pets import builder

    dev = builder.resolve_device(device)
    cfg, spec, model = builder.load_model(run_dir, dev)
    return {
        "run_dir": run_dir,
        "data_label": str(data) if isinstance(data, (str, Path)) else None,
        "arrays": arrays,
        "horizons": horizons,
        "starts": starts,
        "mode": mode,
        "device": dev,
        "cfg": cfg,
        "spec": spec,
        "model": model,
        "obs_std": obs_std(train_arrays),
        "standardized_by": standardized_by,
    }


def evaluate(
    run_dir: str | Path,
    data: str | Path | Mapping[str, np.ndarray],
    horizons: Sequence[int] = DEFAULT_HORIZONS,
    starts: int = DEFAULT_STARTS,
    seed: int = 0,
    mode: str = "mean",
    device: str = "auto",
    log: Any = None,
    train_data: str | Path | Mapping[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Long-horizon prediction errors of the model in ``run_dir`` on data set ``data`` (see the module docstring).

    ``train_data`` (a data set file or its arrays; default: ``data`` itself): the data whose per-entry
    observation std scales ``standardized_error``, normally the model's training data.

    Returns ``{"run", "data", "env", "model", "mode", "seed", "starts", "start_points", "skipped_horizons",
    "standardized_by", "horizons": {"h": {key: value for key in HORIZON_KEYS}}}`` (JSON-ready; horizon keys
    are strings; ``standardized_by``: the train_data path, "arrays" or "test data"). ``log(message)`` gets
    the skip messages (default: stderr). ValueError / ConfigError for bad input.
    """
    return evaluate_loaded(load_inputs(run_dir, data, horizons, starts, mode, device, train_data), seed, log)


def evaluate_loaded(inputs: Mapping[str, Any], seed: int = 0, log: Any = None) -> dict[str, Any]:
    """:func:`evaluate` on the output of :func:`load_inputs`."""
    import torch

    log = log or (lambda message: print(message, file=sys.stderr))
    arrays, spec, dev, mode = inputs["arrays"], inputs["spec"], inputs["device"], inputs["mode"]
    lengths = np.asarray(arrays["lengths"])
    longest = int(lengths.max())
    skipped = [h for h in inputs["horizons"] if h > longest]
    horizons = [h for h in inputs["horizons"] if h <= longest]
    if skipped:
        log(f"{PROG}: skipping horizons {skipped}: longer than every episode (longest {longest} steps)")
    big = horizons[-1]
    pairs = sample_starts(lengths, big, inputs["starts"], np.random.default_rng(seed))
    if len(pairs) < inputs["starts"]:
        log(f"{PROG}: only {len(pairs)} start points leave room for horizon {big}; using all of them")

    ep, t0 = pairs[:, 0], pairs[:, 1]
    steps = t0[:, None] + np.arange(big + 1)[None, :]  # (K, H + 1)
    true_obs = torch.as_tensor(np.asarray(arrays["obs"])[ep[:, None], steps], dtype=torch.float64, device=dev)
    acts = torch.as_tensor(np.asarray(arrays["act"])[ep[:, None], steps[:, :-1]], dtype=torch.float32, device=dev)
    generator = torch.Generator(device=dev).manual_seed(int(seed))
    pred = inputs["model"].rollout(true_obs[:, 0].float(), acts, mode, generator)
    pred = pred.double()  # (K, H, obs_dim)
    errs = step_errors(pred, true_obs[:, 1:], spec.layout, inputs["obs_std"])  # each (K, H)
    finite = torch.isfinite(pred).all(dim=-1)
    own = own_step_errors(pred, true_obs[:, 1:], spec.layout)  # the registered metrics, each (K, H)

    results: dict[str, dict[str, float]] = {}
    for h in horizons:
        row = {
            "mean_step_error": float(errs["total"][:, :h].mean()),
            "final_step_error": float(errs["total"][:, h - 1].mean()),
        }
        for part in (*PARTS, "standardized"):
            row[f"{part}_error"] = float(errs[part][:, :h].mean())
        for name, err in own.items():
            row[name] = float(err[:, :h].mean())
        row["nonfinite_fraction"] = float((~finite[:, :h]).double().mean())
        results[str(h)] = row
    return {
        "run": str(inputs["run_dir"]),
        "data": inputs["data_label"],
        "env": spec.name,
        "model": str(inputs["cfg"].head),
        "mode": mode,
        "seed": int(seed),
        "starts": int(len(pairs)),
        "start_points": pairs.tolist(),
        "skipped_horizons": skipped,
        "standardized_by": inputs["standardized_by"],
        "horizons": results,
    }


def format_table(result: Mapping[str, Any]) -> str:
    """The per-horizon errors as a fixed-width text table: the built-in metrics, then the registered ones."""
    first = next(iter(result["horizons"].values()), {})
    names = (*METRICS, *(k for k in first if k not in HORIZON_KEYS))
    widths = [max(12, len(m)) for m in names]
    head = f"{'horizon':>7}  " + "  ".join(f"{m:>{w}}" for m, w in zip(names, widths))
    lines = [f"{result['env']} / {result['model']} / {result['mode']} / {result['starts']} starts", head]
    for h, row in result["horizons"].items():
        lines.append(f"{h:>7}  " + "  ".join(f"{row[m]:>{w}.6g}" for m, w in zip(names, widths)))
    return "\n".join(lines)


def write_events(run_dir: str | Path, data: str | Path, result: Mapping[str, Any]) -> Path:
    """The per-horizon errors of ``result`` as TensorBoard scalars ``eval/METRIC`` at step = horizon, in
    ``RUN/eval/DATA_STEM`` (``purge_step=0``: an earlier evaluation there is hidden, not repeated)."""
    from pets.runs.tblog import ScalarLog

    log_dir = Path(run_dir) / "eval" / Path(data).stem
    with ScalarLog(log_dir, purge_step=0) as events:
        for h, row in result["horizons"].items():
            events.scalars({f"eval/{key}": value for key, value in row.items()}, int(h))
    return log_dir
