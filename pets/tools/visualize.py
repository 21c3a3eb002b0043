"""The GEM paper's trajectory figure: the true simulator and each model's open-loop prediction, rendered by MuJoCo.

    python -m pets.visualize --runs RUN_A [RUN_B ...] --data TEST.npz [--env ENV] [--steps 0,15,45]
                             [--episode I] [--start T] [--labels A,B] [--root model|truth] [--mode mean|sample]
                             [--seed S] [--size 240x180] [--device D] [--threads N] --out FIG.png

Rows: the truth, then one row per run (labelled); columns: the chosen steps k of one open-loop rollout.

- Truth: the recorded observations ``obs[I, T + k]`` of the data set (:mod:`pets.data.datasets`), i.e. the
  simulator's own states (every catalogue observation holds the whole ``qpos``: :mod:`envs.render`).
- Models: from the same start ``obs[I, T]``, each run's model is rolled out open loop with the recorded actions
  ``act[I, T:T + K]`` (``DynamicsModel.rollout``, as ``pets.evaluate`` does; ``mean``: the elites' mean
  prediction, ``sample``: TS-inf), and the predicted observations are turned into ``qpos`` through the env's
  layout (:func:`envs.render.qpos_from_obs`). Step 0 is the start state in every row.
- Root position: the models never see the root x (and y: Ant, Humanoid) as an input but predict its change.
  ``--root model`` (default) draws the predicted root; ``--root truth`` takes the root x (y) of the truth
  instead, so that only the posture is the model's. The caption says which.
- Camera: per env (:data:`envs.render.CAMERAS`); for the locomotion envs it follows the TRUE root in every row,
  so a model's drift in x shows as a shift against the truth.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pets.runs.fileio import atomic_write_bytes, run_dir_error, writable_dir_error
from pets.tools.cli import OneLineParser, add_threads_option, fail, set_threads, write_failed

PROG = "pets.visualize"
DEFAULT_STEPS = (0, 15, 45)
ROOT_SOURCES = ("model", "truth")
#: Figure layout in pixels around the panels: row label column, column-title band, caption margin and line height.
LABEL_W, TITLE_H, CAPTION_PAD, CAPTION_LINE_H = 110, 28, 10, 14
DPI = 100
CAPTION_FONT = 8


def parse_steps(text: str) -> list[int]:
    """``"0,15,45"`` -> ``[0, 15, 45]`` (in the given order, unique); ValueError unless ints >= 0."""
    message = f"--steps must be comma-separated ints >= 0 such as 0,15,45, got {text!r}"
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(message) from None
    if not values or min(values) < 0 or len(set(values)) != len(values):
        raise ValueError(message)
    return values


def parse_size(text: str) -> tuple[int, int]:
    """``"240x180"`` -> ``(240, 180)`` (width, height); ValueError unless both are ints in [16, 2048]."""
    width, sep, height = text.lower().partition("x")
    try:
        w, h = int(width), int(height)
    except ValueError:
        w = h = 0
    if not sep or not (16 <= w <= 2048 and 16 <= h <= 2048):
        raise ValueError(f"--size must be WIDTHxHEIGHT in pixels (16..2048 each), such as 240x180, got {text!r}")
    return w, h


def wrap_caption(caption: str, figure_width: int) -> list[str]:
    """The caption's lines at :data:`CAPTION_FONT` points in a figure ``figure_width`` pixels wide."""
    import textwrap

    return textwrap.wrap(caption, width=max(20, int(figure_width / (CAPTION_FONT * 0.62 * DPI / 72))))


def figure_size(rows: int, cols: int, width: int, height: int, caption_lines: int = 1) -> tuple[int, int]:
    """The figure's (width, height) in pixels for ``rows`` x ``cols`` panels of ``width`` x ``height`` pixels and
    a caption of ``caption_lines`` lines."""
    return LABEL_W + cols * width, TITLE_H + rows * height + CAPTION_PAD + caption_lines * CAPTION_LINE_H


def root_note(spec: Any, root: str) -> str:
    """The caption's sentence on the root position: where it comes from and what the camera follows ("" for the
    envs whose root is fixed or fully modelled: the pendulums, Reacher)."""
    from envs.render import CAMERAS

    if not spec.layout.invariant:
        return ""
    coords = "x, y" if len(spec.layout.invariant) > 1 else "x"
    where = "the true trajectory" if root == "truth" else "each model's own prediction"
    camera = "; the camera follows the true root" if CAMERAS[spec.name].track else ""
    return f" Root {coords} from {where}{camera}."


def predicted_observations(
    run_dirs: Sequence[str | Path],
    obs0: np.ndarray,
    actions: np.ndarray,
    mode: str = "mean",
    seed: int = 0,
    device: str = "cpu",
) -> list[tuple[Any, np.ndarray]]:
    """For each run: ``(cfg, states)``, states ``(H + 1, obs_dim)`` = the start ``obs0`` then the model's open-loop
    predictions under ``actions`` (H, act_dim). ConfigError for a run that is not a trained run directory."""
    import torch

    from pets import builder

    dev = builder.resolve_device(device)
    out = []
    for run in run_dirs:
        cfg, _, model = builder.load_model(run, dev)
        generator = torch.Generator(device=dev).manual_seed(int(seed))
        start = torch.as_tensor(obs0[None], dtype=torch.float32, device=dev)
        acts = torch.as_tensor(actions[None], dtype=torch.float32, device=dev)
        with torch.no_grad():
            pred = model.rollout(start, acts, mode, generator)[0].double().cpu().numpy()
        out.append((cfg, np.concatenate([np.asarray(obs0, np.float64)[None], pred])))
    return out


def render_rows(
    spec: Any, rows: Sequence[np.ndarray], steps: Sequence[int], root: str = "model", size: tuple[int, int] = (240, 180)
) -> np.ndarray:
    """Frames ``(len(rows), len(steps), height, width, 3)`` uint8. ``rows[0]`` is the truth, every row an array of
    observations ``(>= max(steps) + 1, obs_dim)``; the camera follows the truth's root; ``root="truth"`` puts the
    truth's root coordinates (the layout's invariant ones) into the other rows first."""
    from envs.render import Renderer, qpos_from_obs

    if root not in ROOT_SOURCES:
        raise ValueError(f"root must be one of {', '.join(ROOT_SOURCES)}, got {root!r}")
    truth = np.asarray(rows[0], np.float64)
    invariant = list(spec.layout.invariant)
    width, height = size
    frames = np.zeros((len(rows), len(steps), height, width, 3), np.uint8)
    with Renderer(spec, width, height) as renderer:
        nq = renderer.model.nq
        for c, k in enumerate(steps):
            anchor = renderer.root(qpos_from_obs(spec, truth[k], nq))
            for r, states in enumerate(rows):
                obs = np.array(states[k], np.float64)
                if r and root == "truth":
                    obs[invariant] = truth[k, invariant]
                if not np.isfinite(obs).all():  # a diverged prediction: a black panel, said in the caption
                    continue
                frames[r, c] = renderer.frame(qpos_from_obs(spec, obs, nq), anchor)
    return frames


def save_figure(
    path: str | Path, frames: np.ndarray, row_labels: Sequence[str], col_labels: Sequence[str], caption: str
) -> tuple[int, int]:
    """The grid as a PNG of exactly :func:`figure_size` pixels (panels unscaled), written atomically; returns
    its (width, height)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nrows, ncols, height, width = frames.shape[:4]
    lines = wrap_caption(caption, LABEL_W + ncols * width)
    fig_w, fig_h = figure_size(nrows, ncols, width, height, len(lines))
    fig = plt.figure(figsize=(fig_w / DPI, fig_h / DPI), dpi=DPI)
    for r in range(nrows):
        for c in range(ncols):  # pasted pixel for pixel (no resampling), origin at the figure's bottom left
            fig.figimage(frames[r, c], xo=LABEL_W + c * width, yo=fig_h - TITLE_H - (r + 1) * height, origin="upper")
    for c, label in enumerate(col_labels):
        x = (LABEL_W + (c + 0.5) * width) / fig_w
        fig.text(x, 1 - TITLE_H / 2 / fig_h, label, ha="center", va="center", fontsize=11)
    for r, label in enumerate(row_labels):
        y = 1 - (TITLE_H + (r + 0.5) * height) / fig_h
        fig.text(LABEL_W / 2 / fig_w, y, label, ha="center", va="center", fontsize=10)
    for i, line in enumerate(lines):
        y = (CAPTION_PAD / 2 + (len(lines) - i - 0.5) * CAPTION_LINE_H) / fig_h
        fig.text(0.5, y, line, ha="center", va="center", fontsize=CAPTION_FONT)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    atomic_write_bytes(Path(path), smaller_png(buf.getvalue()))
    return fig_w, fig_h


def smaller_png(png: bytes) -> bytes:
    """The same pixels, smaller: RGB without matplotlib's opaque alpha channel, zlib at its best (Pillow, which
    matplotlib requires)."""
    import io

    from PIL import Image

    out = io.BytesIO()
    Image.open(io.BytesIO(png)).convert("RGB").save(out, format="PNG", optimize=True)
    return out.getvalue()


def visualize(
    run_dirs: Sequence[str | Path],
    data: str | Path,
    out: str | Path,
    steps: Sequence[int] = DEFAULT_STEPS,
    episode: int = 0,
    start: int = 0,
    labels: Sequence[str] | None = None,
    root: str = "model",
    mode: str = "mean",
    seed: int = 0,
    size: tuple[int, int] = (240, 180),
    device: str = "cpu",
    env: str | None = None,
) -> dict[str, Any]:
    """Render the grid (module docstring) to ``out``; returns ``{"frames", "labels", "caption", "size"}``.

    ValueError / ConfigError (one-line messages) for bad input: a data set of another env than a run's or of your own
    env (``module:ATTR``: no camera, no known qpos), an episode too short for the steps, labels that do not match
    the runs.
    """
    import envs
    from envs.render import CAMERAS
    from pets.config import load_config
    from pets.data.datasets import env_name, load_dataset

    arrays = load_dataset(data)
    data_env = env_name(arrays)
    if env is not None and envs.get(env).name != data_env:
        raise ValueError(f"--env {env} does not match the data set, which is from {data_env}")
    if data_env not in CAMERAS:  # a model's predicted observations become a picture through the catalogue's qpos
        raise ValueError(
            f"the data set is from your own env {data_env}: pets.visualize draws the catalogue envs only "
            f"({', '.join(CAMERAS)}), whose observations hold the whole qpos (docs/visualize.md)"
        )
    for run in run_dirs:
        run_env = str(load_config(str(Path(run) / "config.yaml")).env)
        if run_env != data_env:
            raise ValueError(f"run {run} models {run_env} but the data set is from {data_env}")
    if labels is not None and len(labels) != len(run_dirs):
        raise ValueError(f"--labels has {len(labels)} names for {len(run_dirs)} runs")
    if labels is not None and not all(label.strip() for label in labels):
        raise ValueError(f"--labels has an empty name: {','.join(labels)!r}; give one name per run")
    lengths = np.asarray(arrays["lengths"])
    if not 0 <= episode < len(lengths):
        raise ValueError(f"--episode must be in [0, {len(lengths) - 1}], got {episode}")
    horizon = max(steps)
    if start < 0:
        raise ValueError(f"--start must be >= 0 (a step of the episode), got {start}")
    if start + horizon > lengths[episode]:
        raise ValueError(
            f"episode {episode} has {lengths[episode]} steps: --start {start} + the last step {horizon} must not "
            "exceed it; pick an earlier --start, shorter --steps or a longer episode"
        )
    spec = envs.get(data_env)
    truth = np.asarray(arrays["obs"])[episode, start : start + horizon + 1]
    actions = np.asarray(arrays["act"])[episode, start : start + horizon]
    predictions = predicted_observations(run_dirs, truth[0], actions, mode, seed, device)
    if labels is None:
        labels = [f"{cfg.head}\n({Path(run).name})" for run, (cfg, _) in zip(run_dirs, predictions)]
    rows = [truth, *(states for _, states in predictions)]
    frames = render_rows(spec, rows, steps, root, size)
    diverged = [label for label, (_, s) in zip(labels, predictions) if not np.isfinite(s[: horizon + 1]).all()]
    draws = f"sample, seed {seed}" if mode == "sample" else mode  # TS-inf draws: the seed makes the figure
    caption = (
        f"{spec.gym_id}, {Path(data).name} episode {episode} from step {start}: open-loop predictions ({draws}) with "
        f"the recorded actions.{root_note(spec, root)}"
        + (f" Non-finite predictions (black): {', '.join(s.splitlines()[0] for s in diverged)}." if diverged else "")
    )
    row_labels = ["truth", *labels]
    figure = save_figure(out, frames, row_labels, [f"t = {k}" for k in steps], caption)
    return {"frames": frames, "labels": row_labels, "caption": caption, "size": figure}


def build_parser() -> OneLineParser:
    p = OneLineParser(
        prog=PROG,
        description="Render the true trajectory and each model's open-loop prediction (MuJoCo) as a grid.",
    )
    p.add_argument("--runs", type=Path, nargs="+", required=True, help="run directories (pets.train or run_pets.py)")
    p.add_argument("--data", type=Path, required=True, help="data set written by pets.collect (the truth)")
    p.add_argument("--env", help="the data set's env (optional; checked against the data and the runs)")
    p.add_argument("--steps", default=",".join(map(str, DEFAULT_STEPS)), help="columns: steps k (default 0,15,45)")
    p.add_argument("--episode", type=int, default=0, help="episode of the data set (default 0)")
    p.add_argument("--start", type=int, default=0, help="step of the episode the rollout starts at (default 0)")
    p.add_argument("--labels", help="comma-separated row labels, one per run (default: model and run name)")
    p.add_argument("--root", choices=ROOT_SOURCES, default="model", help="root x (y) from the model (default)")
    p.add_argument("--mode", choices=("mean", "sample"), default="mean", help="mean (default) or sample (TS-inf)")
    p.add_argument("--seed", type=int, default=0, help="seed of --mode sample (default 0)")
    p.add_argument("--size", default="240x180", help="panel WIDTHxHEIGHT in pixels (default 240x180)")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu", help="where the models run")
    add_threads_option(p)
    p.add_argument("--out", type=Path, required=True, help="PNG to write (atomically)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        steps = parse_steps(args.steps)
        size = parse_size(args.size)
    except ValueError as err:
        fail(PROG, str(err))
    for run in args.runs:
        if problem := run_dir_error(run):
            fail(PROG, problem)
    from pets.data.datasets import missing_data_file

    if problem := missing_data_file(args.data):
        fail(PROG, problem)
    if args.out.suffix.lower() != ".png":
        fail(PROG, f"--out must name a .png file, got {args.out}")
    if args.out.is_dir():
        fail(PROG, f"--out {args.out} is a directory; give a file name")
    problem = writable_dir_error(args.out.parent)
    if problem:
        fail(PROG, f"cannot write --out {args.out}: {problem}")
    labels = None if args.labels is None else [s.strip() for s in args.labels.split(",")]
    set_threads(args.threads)
    from omegaconf.errors import OmegaConfBaseException

    from envs.render import RenderingUnavailable

    try:
        result = visualize(
            args.runs,
            args.data,
            args.out,
            steps,
            args.episode,
            args.start,
            labels,
            args.root,
            args.mode,
            args.seed,
            size,
            args.device,
            args.env,
        )
    except (ValueError, OmegaConfBaseException) as err:  # ConfigError is a ValueError
        fail(PROG, str(err))
    except RenderingUnavailable as err:  # no usable headless GL here (as device=cuda without CUDA: exit 2)
        fail(PROG, str(err))
    except OSError as err:  # writing the figure failed (a full disk): the temporary file is removed
        write_failed(PROG, err, "no figure was written; free space or pick another --out")
    width, height = result["size"]
    print(f"{args.out}: {len(result['labels'])} rows x {len(steps)} steps, {width}x{height} pixels")
    return 0


if __name__ == "__main__":
    sys.exit(main())
