"""Long-horizon prediction error of a trained model on recorded trajectories (the paper's offline evaluation).

    python -m pets.evaluate --run RUN_DIR --data FILE.npz [--horizons 1,5,10,25,50] [--starts K] [--seed S]
                            [--mode mean|sample] [--device D] [--json OUT.json]

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

Step-wise error ``e_k`` (:func:`step_errors`): Euclidean in observation space with the differences taken
on the groups: ``SO2_angle`` differences wrapped to (-pi, pi], ``SO3_quat`` compared up to sign
(``min(|q - q'|, |q + q'|)``), everything else plain. It is split into a ``position`` part (all group
coordinates of the layout), a ``velocity`` part (``layout.velocities``) and an ``other`` part
(``layout.other`` and ``layout.derived``); ``total^2 = position^2 + velocity^2 + other^2``.

Per horizon h: ``mean_step_error`` = mean over starts and over k = 1..h of ``e_k`` (the paper's average
step-wise error), ``final_step_error`` = mean over starts of ``e_h``; ``position_error``,
``velocity_error``, ``other_error`` = the same average as ``mean_step_error`` for each part;
``nonfinite_fraction``: the share of (start, step) pairs whose prediction is not finite (a diverging
model: those make the averages inf/NaN, reported as such, never hidden).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pets.cli import OneLineParser, fail
from pets.datasets import env_name, load_dataset
from pets.fileio import atomic_write_bytes, writable_dir_error

if TYPE_CHECKING:
    from torch import Tensor

    from envs.layout import ObsLayout

PROG = "pets.evaluate"
DEFAULT_HORIZONS = (1, 5, 10, 25, 50)
DEFAULT_STARTS = 1000
MODES = ("mean", "sample")
METRICS = ("mean_step_error", "final_step_error", "position_error", "velocity_error", "other_error")


# --------------------------------------------------------------------------- metric
def wrap_angle(d: Tensor) -> Tensor:
    """Angle difference wrapped to (-pi, pi]: :func:`gem_head.lie.wrap_angle`, the wrap of the GEM head's targets."""
    from gem_head.lie import wrap_angle

    return wrap_angle(d)


def squared_errors(pred: Tensor, true: Tensor, layout: ObsLayout) -> dict[str, Tensor]:
    """Squared step-wise error parts, each of shape ``(...)`` for ``(..., obs_dim)`` inputs.

    position = sum over groups: Rn and SO2_cossin ``|x - x'|^2``, SO2_angle ``wrap(x - x')^2``,
    SO3_quat ``min(|q - q'|^2, |q + q'|^2)``; velocity = ``|v - v'|^2`` on ``layout.velocities``;
    other = ``|o - o'|^2`` on ``layout.other`` and ``layout.derived``.
    """
    import torch

    if pred.shape != true.shape or pred.shape[-1] != layout.obs_dim:
        raise ValueError(
            f"pred and true must have the same shape (..., obs_dim={layout.obs_dim}), "
            f"got {tuple(pred.shape)} and {tuple(true.shape)}"
        )
    dev = pred.device

    def idx(ix: Sequence[int]) -> Tensor:
        return torch.tensor(list(ix), dtype=torch.long, device=dev)

    plain = [i for g in layout.groups if g.kind in ("Rn", "SO2_cossin") for i in g.indices]
    angles = [g.indices[0] for g in layout.groups if g.kind == "SO2_angle"]
    quats = [g.indices for g in layout.groups if g.kind == "SO3_quat"]
    zero = pred.new_zeros(pred.shape[:-1])

    def sq(ix: Sequence[int]) -> Tensor:
        if not ix:
            return zero
        i = idx(ix)
        return (pred.index_select(-1, i) - true.index_select(-1, i)).pow(2).sum(-1)

    position = sq(plain)
    if angles:
        i = idx(angles)
        position = position + wrap_angle(pred.index_select(-1, i) - true.index_select(-1, i)).pow(2).sum(-1)
    if quats:
        i = idx([k for q in quats for k in q])
        q = pred.index_select(-1, i).unflatten(-1, (len(quats), 4))
        q_true = true.index_select(-1, i).unflatten(-1, (len(quats), 4))
        minus, plus = (q - q_true).pow(2).sum(-1), (q + q_true).pow(2).sum(-1)
        position = position + torch.minimum(minus, plus).sum(-1)
    return {"position": position, "velocity": sq(layout.velocities), "other": sq(layout.other + layout.derived)}


def step_errors(pred: Tensor, true: Tensor, layout: ObsLayout) -> dict[str, Tensor]:
    """Step-wise errors ``total``, ``position``, ``velocity``, ``other`` (square roots of :func:`squared_errors`);
    ``total = sqrt(position^2 + velocity^2 + other^2)``."""
    sq = squared_errors(pred, true, layout)
    total = (sq["position"] + sq["velocity"] + sq["other"]).sqrt()
    return {"total": total, **{k: v.sqrt() for k, v in sq.items()}}


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
) -> dict[str, Any]:
    """Validate the arguments of :func:`evaluate` and load the model and data (ValueError / ConfigError if bad)."""
    from pets.config import ConfigError, load_config

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
    config_file = Path(run_dir) / "config.yaml"  # pets.rundir.CONFIG_FILE (rundir imports torch)
    if not config_file.is_file():
        raise ConfigError(f"{run_dir} is not a run directory (no config.yaml)")
    run_env = str(load_config(str(config_file)).env)  # env check before the model is built
    if env_name(arrays) != run_env:
        raise ValueError(f"the data set is from {env_name(arrays)} but run {run_dir} models {run_env}")
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
) -> dict[str, Any]:
    """Long-horizon prediction errors of the model in ``run_dir`` on data set ``data`` (see the module docstring).

    Returns ``{"run", "data", "env", "model", "mode", "seed", "starts", "start_points", "skipped_horizons",
    "horizons": {"h": {metric: value}}}`` (JSON-ready; horizon keys are strings). ``log(message)`` gets
    the skip messages (default: stderr). ValueError / ConfigError for bad input.
    """
    return evaluate_loaded(load_inputs(run_dir, data, horizons, starts, mode, device), seed, log)


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
    errs = step_errors(pred, true_obs[:, 1:], spec.layout)  # each (K, H)
    finite = torch.isfinite(pred).all(dim=-1)

    results: dict[str, dict[str, float]] = {}
    for h in horizons:
        results[str(h)] = {
            "mean_step_error": float(errs["total"][:, :h].mean()),
            "final_step_error": float(errs["total"][:, h - 1].mean()),
            "position_error": float(errs["position"][:, :h].mean()),
            "velocity_error": float(errs["velocity"][:, :h].mean()),
            "other_error": float(errs["other"][:, :h].mean()),
            "nonfinite_fraction": float((~finite[:, :h]).double().mean()),
        }
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
        "horizons": results,
    }


def format_table(result: Mapping[str, Any]) -> str:
    """The per-horizon errors as a fixed-width text table."""
    head = f"{'horizon':>7}  " + "  ".join(f"{m:>16}" for m in METRICS)
    lines = [f"{result['env']} / {result['model']} / {result['mode']} / {result['starts']} starts", head]
    for h, row in result["horizons"].items():
        lines.append(f"{h:>7}  " + "  ".join(f"{row[m]:>16.6g}" for m in METRICS))
    return "\n".join(lines)


def build_parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description="Long-horizon prediction error of a trained model on recorded data.")
    p.add_argument("--run", type=Path, required=True, help="run directory (run_pets.py or pets.train)")
    p.add_argument("--data", type=Path, required=True, help="data set written by pets.collect")
    p.add_argument(
        "--horizons", default=",".join(map(str, DEFAULT_HORIZONS)), help="comma-separated (default 1,5,10,25,50)"
    )
    p.add_argument("--starts", type=int, default=DEFAULT_STARTS, help=f"start points K (default {DEFAULT_STARTS})")
    p.add_argument("--seed", type=int, default=0, help="seed of the start points and of sampling (default 0)")
    p.add_argument("--mode", choices=MODES, default="mean", help="mean (ensemble mean, default) or sample (TS-inf)")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="auto", help="where the model runs")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (default 0: torch's default)")
    p.add_argument("--json", type=Path, help="write the results as JSON here (atomically)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        horizons = parse_horizons(args.horizons)
    except ValueError as err:
        fail(PROG, str(err))
    if args.starts < 1:
        fail(PROG, f"--starts must be >= 1, got {args.starts}")
    if args.threads < 0:
        fail(PROG, f"--threads must be >= 0 (0: torch's default), got {args.threads}")
    if not (args.run / "config.yaml").is_file():
        fail(PROG, f"{args.run} is not a run directory (no config.yaml)")
    if not args.data.is_file():
        fail(PROG, f"data file {args.data} does not exist")
    problem = None if args.json is None else writable_dir_error(args.json.parent)
    if problem:
        fail(PROG, f"cannot write --json {args.json}: {problem}")

    from omegaconf.errors import OmegaConfBaseException

    from pets.config import ConfigError

    try:  # bad input fails here in one line; errors in the evaluation itself keep their traceback
        inputs = load_inputs(args.run, args.data, horizons, args.starts, args.mode, args.device)
    except (ValueError, ConfigError, OmegaConfBaseException) as err:  # the last: a config.yaml off the schema
        fail(PROG, str(err))
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    result = evaluate_loaded(inputs, args.seed)
    print(format_table(result))
    if args.json is not None:
        atomic_write_bytes(args.json, (json.dumps(result, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
