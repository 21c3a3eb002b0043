"""A/B comparisons of dynamics heads over envs and seeds, with bootstrap statistics and plots.

    python -m pets.compare online  --envs E1,E2 --models M1,M2 --seeds 0,1,2 --trials N --out DIR
                                   [--planners cem,icem] [--workers K] [--preset research|fast]
                                   [--final-window W] [--device D] [--quiet] [key=value ...]
    python -m pets.compare offline --envs E1,E2 --models M1,M2 --seeds 0,1,2 --out DIR
                                   [--episodes E] [--test-episodes E2] [--max-steps T]
                                   [--policy random|smooth-random[:BETA]|existing] [--horizons 1,5,10,25,50]
                                   [--starts K]
                                   [--openloop] [--planners cem,mppi] [--openloop-steps 50] [--openloop-episodes 5]
                                   [--workers K] [--preset research|fast] [--device D] [--quiet] [key=value ...]

Models are the names in ``pets.config.HEADS`` (read at run time); envs are catalogue names or
gymnasium ids. Every (env, model, seed) has its run directory ``DIR/runs/ENV-MODEL-sSEED``.
Everything is resumable: rerunning a command reuses finished work and runs only what is missing.
A run directory that was made with a different config than the command asks for (other
overrides, preset, ...; the trial count aside) is an error (exit 2): results of different configs
are never mixed. Bad lists, envs, models or keys exit 2 with one line; a failed run is reported,
the others go on, the summary covers the finished runs, and the exit status is 1.

online
    Per run: reuse it if ``metrics.csv`` has at least N rows, resume it (``run_pets.py --resume DIR
    --trials N``) if it has fewer, start it (``run_pets.py --env --model --seed --trials N --out DIR
    --preset P threads=1 key=value ...``) if it does not exist. Runs go to a pool of K local
    subprocesses, one torch thread each (``threads=1``, ``OMP_NUM_THREADS=1``); their output goes to
    ``DIR/logs/ENV-MODEL-sSEED.log``. Only the first N trials of a run enter the summary. A user
    ``threads=`` override is ignored (every run gets one thread).

    Per run: ``final`` = mean episode reward of the last W trials (W = ``--final-window``, default 3,
    at most N); ``auc`` = mean episode reward over all N trials (the area under the reward-per-trial
    curve divided by N); the run's wall-clock time and median seconds per planning step. Per (env, model)
    over seeds: mean, 95 % percentile-bootstrap CI and IQM (:mod:`pets.stats`) of final and auc, means
    of the rest. Files: ``summary.md``, ``summary.csv`` (per env and model), ``summary_runs.csv`` (per
    run), ``rewards_ENV.png`` (episode reward vs env steps per model: every seed's curve interpolated
    linearly onto a common grid of 200 env-step values spanning the range that all seeds of the model
    cover, then the mean over seeds with the pointwise bootstrap band; each seed's raw curve faintly
    behind it) and ``walltime_ENV.png`` (the same against the run's wall-clock hours: reward per unit
    of compute, e.g. for planners or heads of different cost).

    ``--planners P1,P2`` makes the planner a second axis: every (model, planner) pair is an arm with
    its runs in ``DIR/runs/ENV-MODEL-PLANNER-sSEED`` (``planner.name=P`` for the run), and the tables
    and plots show ``MODEL+PLANNER``. Wall-clock figures compare fairly only between runs that shared
    the machine alike (one worker per core, no other load).

offline
    Per env: a training and a separate test data set with ``pets.collect`` (``DIR/data/ENV-train.npz``
    with data seed 0 and E episodes, ``DIR/data/ENV-test.npz`` with data seed 1 and E2 episodes, same
    policy), reused if present (an error if they were collected with another policy, seed or episode
    count). ``--policy existing`` takes both files as they are (e.g. collected from a trained agent with
    ``pets.collect --policy run:RUN_DIR --out DIR/data/ENV-train.npz``); then the data options are unused.

    Per run: train offline (``pets.train.train_offline``, model seed = the run's seed) unless the
    run directory holds a trained model; evaluate on the test data (``pets.evaluate``, mean mode, the
    same start points for every model and seed of an env: evaluation seed 0) into ``eval.json`` unless it
    holds this evaluation already; with ``--openloop``, open-loop planning (``pets.openloop``, seed 2)
    per planner into ``openloop_PLANNER.json``. Jobs run in a pool of K processes (one torch thread each)
    or, with K = 1, in this process.

    Files: ``prediction.md``, ``prediction.csv`` (per env, model and horizon: the mean step-wise error
    ``mean_step_error`` over seeds with its 95 % bootstrap CI and IQM), ``prediction_runs.csv`` (per
    run and horizon), ``relative_error.png`` (the paper's Fig. 2: per env one bar per model, the
    step-wise error averaged over the horizons, divided by the largest model's value in that env, so
    the worst model is 1; error bars: the CI divided by the same number), ``absolute_error_ENV.png``
    (Fig. 3: error vs horizon per model with CI bands; log y axis when the values span a factor 10 or
    more). With ``--openloop``: ``openloop.md``, ``openloop.csv`` (per env, planner and model: the mean
    reward per step and the total reward of the open-loop plans, mean and CI over seeds) and
    ``openloop_ENV.png`` (reward vs step per model, one panel per planner).
"""

from __future__ import annotations

import csv
import importlib
import io
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

from pets.cli import OneLineParser, fail
from pets.fileio import atomic_write_bytes

PROG = "pets.compare"
ROOT = Path(__file__).resolve().parents[1]
EXIT_FAILED = 1
#: Data seeds of the offline mode: training data, test data, open-loop initial states.
TRAIN_DATA_SEED, TEST_DATA_SEED, OPENLOOP_SEED = 0, 1, 2
#: Seed of the start points of the prediction-error evaluation (the same for every model and seed).
EVAL_SEED = 0
BOOT_SEED = 0
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


class UsageError(ValueError):
    """A bad argument or an inconsistent output directory: exit 2 with this one-line message."""


# =========================================================================== argument lists
def split_list(text: str, what: str) -> list[str]:
    """``"a,b"`` -> ``["a", "b"]`` (order kept, duplicates dropped); UsageError if empty or with empty items."""
    items = [t.strip() for t in str(text).split(",")]
    if not text or not all(items):
        raise UsageError(f"--{what} must be a comma-separated list without empty items, got {text!r}")
    return list(dict.fromkeys(items))


def parse_envs(text: str) -> list[str]:
    """Canonical env names of a comma-separated list (catalogue names or gymnasium ids)."""
    import envs

    out = []
    for name in split_list(text, "envs"):
        try:
            out.append(envs.canonical_name(name))
        except ValueError as err:
            raise UsageError(str(err)) from None
    return list(dict.fromkeys(out))


def _parse_choices(text: str, what: str, accepted: tuple[str, ...]) -> list[str]:
    """Comma-separated names for ``--what``, each one of ``accepted``."""
    names = split_list(text, what)
    bad = [n for n in names if n not in accepted]
    if bad:
        raise UsageError(f"unknown {what[:-1]} {bad[0]!r} in --{what}; accepted: {', '.join(accepted)}")
    return names


def parse_models(text: str) -> list[str]:
    """Model (head) names, each one of ``pets.config.HEADS`` (read now, so new heads are accepted)."""
    from pets import config

    return _parse_choices(text, "models", config.HEADS)


def parse_seeds(text: str) -> list[int]:
    """Seeds: comma-separated ints >= 0."""
    items = split_list(text, "seeds")
    try:
        seeds = [int(s) for s in items]
    except ValueError:
        raise UsageError(f"--seeds must be comma-separated ints >= 0 such as 0,1,2, got {text!r}") from None
    if min(seeds) < 0:
        raise UsageError(f"--seeds must be ints >= 0, got {text!r}")
    return list(dict.fromkeys(seeds))


def parse_planners(text: str) -> list[str]:
    """Planner names, each one of ``pets.config.PLANNERS``."""
    from pets import config

    return _parse_choices(text, "planners", config.PLANNERS)


def run_name(env: str, model: str, seed: int, planner: str | None = None) -> str:
    """The run directory's name: ``ENV-MODEL-sSEED``, or ``ENV-MODEL-PLANNER-sSEED`` when planners are compared."""
    return f"{env}-{model}-s{seed}" if planner is None else f"{env}-{model}-{planner}-s{seed}"


def arm_label(model: str, planner: str | None) -> str:
    """What the summaries call one compared arm: the model, or ``MODEL+PLANNER`` when planners are compared."""
    return model if planner is None else f"{model}+{planner}"


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def config_differences(run_dir: Path, expected: Any, ignore: Iterable[str] = ("trials",)) -> list[str]:
    """``key: found != expected`` for every config key where ``run_dir/config.yaml`` differs from ``expected``."""
    from omegaconf import OmegaConf

    from pets.config import load_config

    found = _flatten(OmegaConf.to_container(load_config(str(run_dir / "config.yaml"))))
    want = _flatten(OmegaConf.to_container(expected))
    skip = set(ignore)
    return [
        f"{k}: {found.get(k)!r} != {want.get(k)!r}"
        for k in sorted(set(found) | set(want))
        if k not in skip and found.get(k) != want.get(k)
    ]


def check_same_config(run_dir: Path, expected: Any, ignore: Iterable[str] = ("trials",)) -> None:
    """UsageError if the run in ``run_dir`` was made with another config than ``expected``."""
    from omegaconf.errors import OmegaConfBaseException

    try:
        diff = config_differences(run_dir, expected, ignore)
    except (ValueError, OmegaConfBaseException) as err:
        raise UsageError(
            f"{run_dir}/config.yaml cannot be read ({str(err).splitlines()[0]}); "
            "move that run directory away or pick another --out"
        ) from None
    if diff:
        raise UsageError(
            f"{run_dir} was made with another config ({'; '.join(diff[:4])}"
            f"{'; ...' if len(diff) > 4 else ''}); pass the same settings or pick another --out"
        )


# =========================================================================== small file helpers
def write_csv(path: Path, rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> None:
    """Write ``rows`` (floats at full precision) atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def fmt(x: float, digits: int = 4) -> str:
    """A number for a markdown table (``nan``/``inf`` spelt out)."""
    if x is None or not math.isfinite(x):
        return str(x)
    return f"{x:.{digits}g}"


def fmt_ci(s: Mapping[str, float]) -> str:
    return f"{fmt(s['mean'])} [{fmt(s['ci_low'])}, {fmt(s['ci_high'])}]"


def md_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def model_colors(models: Sequence[str]) -> dict[str, Any]:
    """A fixed colour per model (its index in ``pets.config.HEADS``), so that every figure agrees."""
    import matplotlib

    from pets import config

    cmap = matplotlib.colormaps["tab10"]
    order = list(config.HEADS) + [m for m in models if m not in config.HEADS]
    return {m: cmap(order.index(m) % 10) for m in models}


def _figure_bytes(fig: Any) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def run_pool(
    jobs: Sequence[tuple[str, Callable[..., Any], tuple]], workers: int, *, processes: bool, progress: bool, desc: str
) -> dict[str, tuple[bool, Any]]:
    """Run ``fn(*args)`` for every ``(name, fn, args)``; ``{name: (ok, result or error message)}``.

    ``processes``: a spawn ProcessPoolExecutor (workers > 1) or this process (workers = 1); else a thread
    pool (for functions that only wait on subprocesses). A job that raises is reported, the rest go on.
    """
    from tqdm.auto import tqdm

    results: dict[str, tuple[bool, Any]] = {}
    if not jobs:
        return results
    bar = tqdm(total=len(jobs), desc=desc, unit="run", disable=not progress, file=sys.stderr)

    def record(name: str, ok: bool, value: Any) -> None:
        results[name] = (ok, value)
        if not ok:
            tqdm.write(f"{PROG}: {name} failed: {value}", file=sys.stderr)
        bar.update(1)

    if processes and workers == 1:
        for name, fn, args in jobs:
            try:
                record(name, True, fn(*args))
            except Exception as err:  # one failed run must not stop the others
                record(name, False, f"{type(err).__name__}: {' '.join(str(err).split())}")
    else:
        if processes:
            import multiprocessing

            pool: Any = ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init
            )
        else:
            pool = ThreadPoolExecutor(max_workers=workers)
        with pool:
            futures: dict[Future, str] = {pool.submit(fn, *args): name for name, fn, args in jobs}
            for fut in as_completed(futures):
                err = fut.exception()
                if err is None:
                    record(futures[fut], True, fut.result())
                else:
                    record(futures[fut], False, f"{type(err).__name__}: {' '.join(str(err).split())}")
    bar.close()
    return results


def _worker_init() -> None:
    """One CPU thread per worker (set before the worker imports torch; the jobs also call set_num_threads(1))."""
    os.environ.update(ONE_THREAD_ENV)


# =========================================================================== online
def online_rows(run_dir: Path) -> list[dict[str, float]]:
    """The metrics rows of a run directory (empty if it has none yet)."""
    from pets import rundir

    path = run_dir / rundir.METRICS_FILE
    return rundir.read_metrics(path) if path.is_file() else []


def online_plan(run_dir: Path, trials: int) -> str:
    """``reuse`` (>= trials rows), ``resume`` (a run with fewer rows) or ``start`` (no run yet)."""
    if not (run_dir / "config.yaml").is_file():
        return "start"
    return "reuse" if len(online_rows(run_dir)) >= trials else "resume"


def online_command(
    action: str, run_dir: Path, env: str, model: str, seed: int, trials: int, preset: str, overrides: Sequence[str]
) -> list[str]:
    """The ``run_pets.py`` command line that starts or resumes one run."""
    script = [sys.executable, str(ROOT / "run_pets.py")]
    if action == "resume":
        return [*script, "--resume", str(run_dir), "--trials", str(trials), "--quiet"]
    return [
        *script,
        "--env",
        env,
        "--model",
        model,
        "--seed",
        str(seed),
        "--trials",
        str(trials),
        "--out",
        str(run_dir),
        "--preset",
        preset,
        "--quiet",
        *overrides,
        "threads=1",
    ]


def run_logged(command: Sequence[str], log: Path) -> int:
    """Run ``command`` with one CPU thread, appending its output to ``log``; raise if it fails."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        f.write(f"\n[{time.strftime('%Y-%m-%d %H:%M:%S')}] {' '.join(command)}\n")
        f.flush()
        proc = subprocess.run(
            command, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, env={**os.environ, **ONE_THREAD_ENV}
        )
    if proc.returncode != 0:
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        raise RuntimeError(f"exit {proc.returncode}; log {log}; last line: {lines[-1] if lines else ''}")
    return proc.returncode


def online_run_stats(rows: Sequence[Mapping[str, float]], trials: int, final_window: int) -> dict[str, float]:
    """Per-run numbers from the first ``trials`` metrics rows: final (mean of the last ``final_window``
    episode rewards), auc (mean episode reward over all trials), env_steps, wall_time_s (the run's
    wall-clock seconds: planning, simulation and model training) and plan_seconds_per_step (median over
    the planned trials; 0 if every trial was random)."""
    use = list(rows)[:trials]
    rewards = np.array([r["episode_reward"] for r in use], dtype=np.float64)
    w = min(final_window, len(use))
    planned = [r["plan_seconds_per_step"] for r in use if r.get("plan_seconds_per_step", 0.0) > 0]
    return {
        "final_reward": float(rewards[-w:].mean()),
        "auc": float(rewards.mean()),
        "env_steps": float(use[-1]["env_steps"]),
        "wall_time_s": float(use[-1]["wall_time_s"]),
        "plan_seconds_per_step": float(np.median(planned)) if planned else 0.0,
    }


def compare_online(
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    trials: int,
    out: Path,
    *,
    workers: int = 1,
    preset: str = "research",
    overrides: Sequence[str] = (),
    final_window: int = 3,
    progress: bool = True,
    planners: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Run (or reuse/resume) every online run, then write the summary. Returns ``{"actions", "failed",
    "summary"}``. UsageError for bad settings or a run directory with another config.

    ``planners``: also compare these planners (``planner.name``); every (model, planner) pair is an arm.
    """
    from pets.config import ConfigError, make_config, parse_overrides

    if trials < 1 or workers < 1 or final_window < 1:
        raise UsageError(
            f"--trials, --workers and --final-window must be >= 1, got {trials}, {workers}, {final_window}"
        )
    try:
        extra = parse_overrides(list(overrides))
    except ConfigError as err:
        raise UsageError(str(err)) from None
    extra.pop("threads", None)  # every run uses one thread
    for key in ("trials", "seed", "head", "env"):
        if key in extra:
            raise UsageError(
                f"{key}= is set by the command itself (--{'models' if key == 'head' else key + 's'}); "
                "do not pass it as an override"
            )
    if planners is not None and "planner.name" in extra:
        raise UsageError("give the planner once: --planners or planner.name=, not both")
    out = Path(out).resolve()
    jobs, actions = [], {}
    for env in env_names:
        for model, planner in online_arms(models, planners):
            arm_extra = extra if planner is None else {**extra, "planner.name": planner}
            arm_list = [f"{k}={v}" for k, v in arm_extra.items()]
            for seed in seeds:
                name = run_name(env, model, seed, planner)
                run_dir = out / "runs" / name
                try:
                    expected = make_config(
                        env, model, preset, {**arm_extra, "seed": seed, "trials": trials, "threads": 1}
                    )
                except ConfigError as err:
                    raise UsageError(str(err)) from None
                action = online_plan(run_dir, trials)
                if action != "start":
                    check_same_config(run_dir, expected)
                    if any(math.isnan(r["trial"]) for r in online_rows(run_dir)):
                        raise UsageError(
                            f"{run_dir} is an offline training run (pets.train), not an online run; "
                            "use separate --out directories for online and offline comparisons"
                        )
                actions[name] = action
                if action != "reuse":
                    cmd = online_command(action, run_dir, env, model, seed, trials, preset, arm_list)
                    jobs.append((name, run_logged, (cmd, out / "logs" / f"{name}.log")))
    counts = {a: sum(1 for v in actions.values() if v == a) for a in ("reuse", "resume", "start")}
    print(
        f"{PROG}: {len(actions)} runs: {counts['reuse']} reused, {counts['resume']} to resume, "
        f"{counts['start']} to start ({workers} worker{'s' if workers > 1 else ''})",
        file=sys.stderr,
    )
    results = run_pool(jobs, min(workers, max(len(jobs), 1)), processes=False, progress=progress, desc="online runs")
    failed = {name: msg for name, (ok, msg) in results.items() if not ok}
    summary = summarise_online(out, env_names, models, seeds, trials, final_window, failed, planners)
    return {"actions": actions, "failed": failed, "summary": summary}


def online_arms(models: Sequence[str], planners: Sequence[str] | None) -> list[tuple[str, str | None]]:
    """The compared (model, planner) pairs; the planner is None when planners are not compared."""
    return [(m, p) for m in models for p in (planners if planners is not None else [None])]


def summarise_online(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    trials: int,
    final_window: int,
    failed: Mapping[str, str] | None = None,
    planners: Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """Write summary.md, summary.csv, summary_runs.csv, rewards_ENV.png and walltime_ENV.png from the complete runs."""
    from pets.stats import summarise

    out = Path(out)
    per_run, summary, missing = [], [], []
    curves: dict[tuple[str, str], list[list[dict[str, float]]]] = {}
    arms = online_arms(models, planners)
    for env in env_names:
        for model, planner in arms:
            label = arm_label(model, planner)
            finals, aucs, stats = [], [], []
            for seed in seeds:
                name = run_name(env, model, seed, planner)
                rows = online_rows(out / "runs" / name)
                if len(rows) < trials:
                    missing.append(
                        f"{name} ({len(rows)}/{trials} trials"
                        f"{'; failed: ' + failed[name] if failed and name in failed else ''})"
                    )
                    continue
                s = online_run_stats(rows, trials, final_window)
                per_run.append(
                    {"env": env, "model": model, "planner": planner or "", "seed": seed, "trials": trials, **s}
                )
                finals.append(s["final_reward"])
                aucs.append(s["auc"])
                stats.append(s)
                curves.setdefault((env, label), []).append(rows[:trials])
            if not finals:
                continue
            f, a = summarise(finals, seed=BOOT_SEED), summarise(aucs, seed=BOOT_SEED)
            summary.append(
                {
                    "env": env,
                    "model": model,
                    "planner": planner or "",
                    "n_seeds": f["n"],
                    "trials": trials,
                    "final_window": min(final_window, trials),
                    "final_mean": f["mean"],
                    "final_ci_low": f["ci_low"],
                    "final_ci_high": f["ci_high"],
                    "final_iqm": f["iqm"],
                    "auc_mean": a["mean"],
                    "auc_ci_low": a["ci_low"],
                    "auc_ci_high": a["ci_high"],
                    "auc_iqm": a["iqm"],
                    **{
                        f"{k}_mean": float(np.mean([s[k] for s in stats]))
                        for k in ("env_steps", "wall_time_s", "plan_seconds_per_step")
                    },
                }
            )
    write_csv(out / "summary.csv", summary, SUMMARY_COLUMNS)
    write_csv(
        out / "summary_runs.csv",
        per_run,
        [
            "env",
            "model",
            "planner",
            "seed",
            "trials",
            "final_reward",
            "auc",
            "env_steps",
            "wall_time_s",
            "plan_seconds_per_step",
        ],
    )
    w = min(final_window, trials)
    text = [
        f"# Online comparison ({trials} trials per run)",
        "",
        f"final = mean episode reward of the last {w} trial{'s' if w > 1 else ''} of each run; "
        f"AUC = mean episode reward over all {trials} trials. Mean over seeds with the 95 % "
        "percentile-bootstrap CI in brackets; IQM = interquartile mean over seeds. Plan s/step: median "
        "seconds per planning step of a run (mean over seeds); wall h: the run's wall-clock hours "
        "(planning, simulation, model training; mean over seeds).",
        "",
    ]
    arm_header = ["model"] if planners is None else ["model", "planner"]
    for env in env_names:
        rows = [r for r in summary if r["env"] == env]
        if not rows:
            continue
        text += [
            f"## {env}",
            "",
            md_table(
                [
                    *arm_header,
                    "seeds",
                    "final reward",
                    "final IQM",
                    "AUC",
                    "AUC IQM",
                    "env steps",
                    "plan s/step",
                    "wall h",
                ],
                [
                    [
                        *([r["model"]] if planners is None else [r["model"], r["planner"]]),
                        str(r["n_seeds"]),
                        fmt_ci({"mean": r["final_mean"], "ci_low": r["final_ci_low"], "ci_high": r["final_ci_high"]}),
                        fmt(r["final_iqm"]),
                        fmt_ci({"mean": r["auc_mean"], "ci_low": r["auc_ci_low"], "ci_high": r["auc_ci_high"]}),
                        fmt(r["auc_iqm"]),
                        f"{r['env_steps_mean']:.0f}",
                        fmt(r["plan_seconds_per_step_mean"], 3),
                        fmt(r["wall_time_s_mean"] / 3600, 3),
                    ]
                    for r in rows
                ],
            ),
            "",
            f"![rewards](rewards_{env}.png) ![wall-clock](walltime_{env}.png)",
            "",
        ]
        labels = [arm_label(m, p) for m, p in arms]
        runs = {label: curves[(env, label)] for label in labels if (env, label) in curves}
        colors = model_colors(list(runs)) if planners is None else arm_colors(list(runs))
        plot_online(out / f"rewards_{env}.png", env, runs, colors)
        plot_online(out / f"walltime_{env}.png", env, runs, colors, x_key="wall_time_s")
    if missing:
        text += ["## Missing or incomplete runs (not in the statistics)", ""] + [f"- {m}" for m in missing] + [""]
    atomic_write_bytes(out / "summary.md", "\n".join(text).encode())
    return summary


SUMMARY_COLUMNS = [
    "env",
    "model",
    "planner",
    "n_seeds",
    "trials",
    "final_window",
    "final_mean",
    "final_ci_low",
    "final_ci_high",
    "final_iqm",
    "auc_mean",
    "auc_ci_low",
    "auc_ci_high",
    "auc_iqm",
    "env_steps_mean",
    "wall_time_s_mean",
    "plan_seconds_per_step_mean",
]

#: x axis of the online plots: metrics column -> (axis label, scale applied to the column).
ONLINE_X = {"env_steps": ("environment steps", 1.0), "wall_time_s": ("wall-clock hours of the run", 1 / 3600)}


def arm_colors(labels: Sequence[str]) -> dict[str, Any]:
    """A colour per compared arm, in order (``tab10``)."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {label: cmap(i % 10) for i, label in enumerate(labels)}


def plot_online(
    path: Path,
    env: str,
    runs: Mapping[str, Sequence[Sequence[Mapping[str, float]]]],
    colors: Mapping[str, Any],
    x_key: str = "env_steps",
) -> None:
    """Episode reward vs env steps (or wall-clock time) per arm: mean over seeds on a common grid, bootstrap
    band (module docstring)."""
    from pets.stats import bootstrap_band

    x_label, x_scale = ONLINE_X[x_key]
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for arm, seed_rows in runs.items():
        c = colors[arm]
        xs = [np.array([r[x_key] for r in rows]) * x_scale for rows in seed_rows]
        ys = [np.array([r["episode_reward"] for r in rows]) for rows in seed_rows]
        for x, y in zip(xs, ys):
            ax.plot(x, y, color=c, alpha=0.2, lw=0.8)
        lo, hi = max(x[0] for x in xs), min(x[-1] for x in xs)
        label = f"{arm} (n={len(seed_rows)})"
        if hi > lo:
            grid = np.linspace(lo, hi, 200)
            curves = np.stack([np.interp(grid, x, y) for x, y in zip(xs, ys)])
            band_low, band_high = bootstrap_band(curves, seed=BOOT_SEED)
            ax.plot(grid, curves.mean(axis=0), color=c, lw=2, label=label)
            ax.fill_between(grid, band_low, band_high, color=c, alpha=0.25, lw=0)
        else:  # one trial, or seeds whose ranges do not overlap: the final points only
            finals = np.array([y[-1] for y in ys])
            ax.errorbar(
                [np.mean([x[-1] for x in xs])],
                [finals.mean()],
                yerr=[[finals.mean() - finals.min()], [finals.max() - finals.mean()]],
                color=c,
                marker="o",
                capsize=4,
                label=label,
            )
    ax.set_xlabel(x_label)
    ax.set_ylabel("episode reward")
    ax.set_title(f"{env}: episode reward (mean over seeds, 95 % bootstrap CI)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, _figure_bytes(fig))


# =========================================================================== offline
#: ``--policy`` value that uses the data files already in DIR/data as they are.
EXISTING = "existing"


def expected_policy_name(policy: str) -> str:
    """The ``policy`` name ``pets.collect`` stores for a ``--policy`` string (random or smooth-random only)."""
    from pets.collect import DEFAULT_BETA, parse_policy

    if policy == EXISTING:
        return EXISTING

    try:
        kind, arg = parse_policy(policy)
    except ValueError as err:
        raise UsageError(str(err)) from None
    if kind == "run":
        raise UsageError(
            "--policy must be random, smooth-random[:BETA] or existing (one policy for every env; "
            "collect agent data with pets.collect --policy run:RUN_DIR into DIR/data and use existing)"
        )
    return "random" if kind == "random" else f"smooth-random:{(DEFAULT_BETA if arg is None else arg):g}"


def prepare_data(
    path: Path, env: str, policy: str, episodes: int, seed: int, max_steps: int | None, progress: bool = False
) -> str:
    """Collect the data set at ``path`` unless it exists; ``"collected"`` or ``"reused"``.

    UsageError if an existing file was collected for another env, policy, seed or episode count.
    """
    import envs
    from pets.collect import collect
    from pets.datasets import load_dataset, save_dataset

    want = {"env": env, "policy": expected_policy_name(policy), "seed": seed, "episodes": episodes}
    if policy == EXISTING and not path.is_file():
        raise UsageError(f"--policy existing needs the data file {path} (e.g. from pets.collect); it does not exist")
    if path.is_file():
        try:
            data = load_dataset(path)
        except ValueError as err:
            raise UsageError(f"{err}; delete it to collect it again") from None
        if policy == EXISTING:
            if str(data["env"]) != env:
                raise UsageError(f"{path} holds {data['env']} data, not {env}")
            return "reused"
        got = {
            "env": str(data["env"]),
            "policy": str(data["policy"]) if "policy" in data else None,
            "seed": int(data["seed"]) if "seed" in data else None,
            "episodes": int(len(data["lengths"])),
        }
        if max_steps is not None and int(data["lengths"].max()) > max_steps:
            got["max_steps"], want["max_steps"] = int(data["lengths"].max()), max_steps
        if got != want:
            diff = "; ".join(f"{k}: {got.get(k)!r} != {want.get(k)!r}" for k in want if got.get(k) != want.get(k))
            raise UsageError(
                f"{path} was collected with other settings ({diff}); pass the same settings, "
                "delete the file or pick another --out"
            )
        return "reused"
    save_dataset(path, collect(envs.get(env), policy, episodes, seed, max_steps, progress=progress))
    return "collected"


def offline_job(job: Mapping[str, Any]) -> dict[str, Any]:
    """One (env, model, seed): train if needed, evaluate if needed, open-loop plan if asked and needed.

    Runs in a worker process (or in this one); returns what it did, ``{"name", "done": [...]}``.
    """
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _offline_job(job)
    finally:
        torch.set_num_threads(threads)


def _offline_job(job: Mapping[str, Any]) -> dict[str, Any]:
    from pets.evaluate import evaluate
    from pets.openloop import open_loop
    from pets.train import train_offline

    run_dir, done = Path(job["run_dir"]), []
    if not (run_dir / "config.yaml").is_file():
        train_offline(
            job["train_data"],
            job["model"],
            run_dir,
            job["overrides"],
            preset=job["preset"],
            seed=job["seed"],
            device=job["device"],
        )
        done.append("train")
    eval_path, request = run_dir / "eval.json", job["eval_request"]
    if "train" in done or not _json_matches(eval_path, request):
        result = evaluate(
            run_dir,
            job["test_data"],
            request["horizons"],
            request["starts"],
            seed=request["seed"],
            mode=request["mode"],
            device=job["device"],
            log=lambda message: None,
        )
        result["request"] = request
        atomic_write_bytes(eval_path, (json.dumps(result) + "\n").encode())
        done.append("eval")
    for planner in job["planners"]:
        path = run_dir / f"openloop_{planner}.json"
        request = {**job["openloop_request"], "planner": planner}
        if "train" in done or not _json_matches(path, request):
            r = request
            result = open_loop(run_dir, planner, r["steps"], r["episodes"], r["seed"], device=job["device"])
            result["request"] = request
            atomic_write_bytes(path, (json.dumps(result) + "\n").encode())
            done.append(f"openloop_{planner}")
    return {"name": run_dir.name, "done": done}


def offline_todo(job: Mapping[str, Any]) -> list[str]:
    """What :func:`offline_job` would do for ``job`` now: a subset of train, eval, openloop_PLANNER."""
    run_dir = Path(job["run_dir"])
    todo = [] if (run_dir / "config.yaml").is_file() else ["train"]
    if todo or not _json_matches(run_dir / "eval.json", job["eval_request"]):
        todo.append("eval")
    todo += [
        f"openloop_{p}"
        for p in job["planners"]
        if todo[:1] == ["train"]
        or not _json_matches(run_dir / f"openloop_{p}.json", {**job["openloop_request"], "planner": p})
    ]
    return todo


def _json_matches(path: Path, request: Mapping[str, Any]) -> bool:
    """Whether ``path`` holds a result made for exactly ``request`` (its ``"request"`` entry)."""
    if not path.is_file():
        return False
    try:
        return json.loads(path.read_text()).get("request") == json.loads(json.dumps(request))
    except (ValueError, AttributeError):
        return False


def compare_offline(
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    out: Path,
    *,
    episodes: int = 100,
    test_episodes: int = 20,
    max_steps: int | None = None,
    policy: str = "random",
    horizons: Sequence[int] = (1, 5, 10, 25, 50),
    starts: int = 1000,
    openloop: bool = False,
    planners: Sequence[str] = ("cem", "mppi"),
    openloop_steps: int = 50,
    openloop_episodes: int = 5,
    workers: int = 1,
    preset: str = "research",
    device: str = "auto",
    overrides: Sequence[str] = (),
    progress: bool = True,
) -> dict[str, Any]:
    """Collect, train, evaluate (and open-loop plan) everything missing, then write the summaries.

    Returns ``{"data": {file: collected|reused}, "todo": {run: [what was missing]}, "done": {run: [what was
    done]}, "failed": {run: message}, "summary"}``; runs absent from "todo" were reused as they were.
    """
    from pets.config import ConfigError, parse_overrides
    from pets.train import offline_config

    for name, value in (
        ("episodes", episodes),
        ("test-episodes", test_episodes),
        ("starts", starts),
        ("workers", workers),
        ("openloop-steps", openloop_steps),
        ("openloop-episodes", openloop_episodes),
    ):
        if value < 1:
            raise UsageError(f"--{name} must be >= 1, got {value}")
    if max_steps is not None and max_steps < 1:
        raise UsageError(f"--max-steps must be >= 1, got {max_steps}")
    expected_policy_name(policy)
    try:
        extra = parse_overrides(list(overrides))
    except ConfigError as err:
        raise UsageError(str(err)) from None
    for key in ("seed", "head", "env", "device"):
        if key in extra:
            raise UsageError(f"{key}= is set by the command itself; do not pass it as an override")
    extra["threads"] = "1"
    out = Path(out).resolve()
    jobs, data_actions, pending = [], {}, {}
    # by its importable name, so that spawned workers can unpickle it also under ``python -m pets.compare``
    job_fn = importlib.import_module("pets.compare").offline_job
    for env in env_names:
        for model in models:
            for seed in seeds:
                run_dir = out / "runs" / run_name(env, model, seed)
                try:
                    expected = offline_config(env, model, extra, preset=preset, seed=seed, device=device)
                except ConfigError as err:
                    raise UsageError(str(err)) from None
                if (run_dir / "config.yaml").is_file():
                    check_same_config(run_dir, expected, ignore=())
    data_dir = out / "data"
    for env in env_names:  # cheap with random policies: done here, before the pool
        for part, seed, n in (("train", TRAIN_DATA_SEED, episodes), ("test", TEST_DATA_SEED, test_episodes)):
            path = data_dir / f"{env}-{part}.npz"
            data_actions[path.name] = prepare_data(path, env, policy, n, seed, max_steps, progress)
    eval_request = {
        "horizons": sorted(set(int(h) for h in horizons)),
        "starts": starts,
        "seed": EVAL_SEED,
        "mode": "mean",
    }
    openloop_request = {"steps": openloop_steps, "episodes": openloop_episodes, "seed": OPENLOOP_SEED}
    for env in env_names:
        for model in models:
            for seed in seeds:
                name = run_name(env, model, seed)
                job = {
                    "env": env,
                    "model": model,
                    "seed": seed,
                    "run_dir": str(out / "runs" / name),
                    "train_data": str(data_dir / f"{env}-train.npz"),
                    "test_data": str(data_dir / f"{env}-test.npz"),
                    "overrides": extra,
                    "preset": preset,
                    "device": device,
                    "eval_request": {**eval_request, "data": f"data/{env}-test.npz"},
                    "planners": list(planners) if openloop else [],
                    "openloop_request": openloop_request,
                }
                todo = offline_todo(job)
                if todo:
                    jobs.append((name, job_fn, (job,)))
                    pending[name] = todo
    total = len(env_names) * len(models) * len(seeds)
    print(
        f"{PROG}: {total} runs: {total - len(jobs)} reused, {len(jobs)} with work to do "
        f"({workers} worker{'s' if workers > 1 else ''}); data: "
        + ", ".join(f"{k} {v}" for k, v in data_actions.items()),
        file=sys.stderr,
    )
    results = run_pool(jobs, min(workers, max(len(jobs), 1)), processes=True, progress=progress, desc="offline runs")
    failed = {name: msg for name, (ok, msg) in results.items() if not ok}
    done = {name: res["done"] for name, (ok, res) in results.items() if ok}
    summary = summarise_offline(out, env_names, models, seeds, eval_request, failed)
    if openloop:
        summarise_openloop(out, env_names, models, seeds, planners, openloop_request)
    return {"data": data_actions, "todo": pending, "done": done, "failed": failed, "summary": summary}


def load_evals(
    out: Path, env: str, models: Sequence[str], seeds: Sequence[int], request: Mapping[str, Any]
) -> dict[str, list[dict[str, Any]]]:
    """{model: [eval.json of each seed that has one for this request]}."""
    found: dict[str, list[dict[str, Any]]] = {}
    for model in models:
        for seed in seeds:
            path = out / "runs" / run_name(env, model, seed) / "eval.json"
            req = {**request, "data": f"data/{env}-test.npz"}
            if _json_matches(path, req):
                found.setdefault(model, []).append({**json.loads(path.read_text()), "seed": seed})
    return found


def summarise_offline(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    request: Mapping[str, Any],
    failed: Mapping[str, str] | None = None,
) -> list[dict[str, Any]]:
    """Write prediction.md, prediction.csv, prediction_runs.csv, relative_error.png, absolute_error_ENV.png."""
    from pets.stats import summarise

    out = Path(out)
    rows, per_run, relative, text = [], [], {}, []
    text += [
        "# Offline comparison: long-horizon prediction error",
        "",
        "Mean step-wise error (pets.evaluate, ensemble-mean rollouts on the test data, the same start "
        "points for every model and seed of an env) per horizon; mean over seeds with the 95 % "
        "percentile-bootstrap CI in brackets.",
        "",
    ]
    for env in env_names:
        evals = load_evals(out, env, models, seeds, request)
        if not evals:
            continue
        common = sorted(set.intersection(*[set(map(int, e["horizons"])) for runs in evals.values() for e in runs]))
        table, curves = [], {}
        for model, runs in evals.items():
            by_h = {h: [float(e["horizons"][str(h)]["mean_step_error"]) for e in runs] for h in common}
            for e in runs:
                for h, m in e["horizons"].items():
                    per_run.append(
                        {"env": env, "model": model, "seed": e["seed"], "horizon": int(h), "starts": e["starts"], **m}
                    )
            stats_h = {}
            for h in common:
                s = summarise(by_h[h], seed=BOOT_SEED)
                finals = [float(e["horizons"][str(h)]["final_step_error"]) for e in runs]
                nonfinite = [float(e["horizons"][str(h)]["nonfinite_fraction"]) for e in runs]
                rows.append(
                    {
                        "env": env,
                        "model": model,
                        "horizon": h,
                        "n_seeds": s["n"],
                        "mean_step_error": s["mean"],
                        "ci_low": s["ci_low"],
                        "ci_high": s["ci_high"],
                        "iqm": s["iqm"],
                        "final_step_error": float(np.mean(finals)),
                        "nonfinite_fraction": float(np.mean(nonfinite)),
                    }
                )
                stats_h[h] = s
            curves[model] = (common, stats_h)
            table.append([model, str(len(runs))] + [fmt_ci(stats_h[h]) for h in common])
            # Fig. 2: per seed the error averaged over the horizons, then the statistics over seeds
            relative.setdefault(env, {})[model] = summarise(
                [float(np.mean([e["horizons"][str(h)]["mean_step_error"] for h in common])) for e in runs],
                seed=BOOT_SEED,
            )
        asked = set(request["horizons"])
        skipped = sorted(asked - set(common))
        note = f"; skipped: {', '.join(map(str, skipped))} (longer than the test episodes)" if skipped else ""
        text += [
            f"## {env} (horizons {', '.join(map(str, common))}{note})",
            "",
            md_table(["model", "seeds"] + [f"h={h}" for h in common], table),
            "",
            f"![absolute error](absolute_error_{env}.png)",
            "",
        ]
        plot_absolute(out / f"absolute_error_{env}.png", env, curves)
    write_csv(
        out / "prediction.csv",
        rows,
        [
            "env",
            "model",
            "horizon",
            "n_seeds",
            "mean_step_error",
            "ci_low",
            "ci_high",
            "iqm",
            "final_step_error",
            "nonfinite_fraction",
        ],
    )
    write_csv(
        out / "prediction_runs.csv",
        per_run,
        [
            "env",
            "model",
            "seed",
            "horizon",
            "starts",
            "mean_step_error",
            "final_step_error",
            "position_error",
            "velocity_error",
            "other_error",
            "nonfinite_fraction",
        ],
    )
    if relative:
        plot_relative(out / "relative_error.png", relative)
        text += [
            "## Relative error (Fig. 2)",
            "",
            "Step-wise error averaged over the horizons, divided by the largest model's mean in the env.",
            "",
            md_table(
                ["env"] + list(models),
                [
                    [env]
                    + [
                        fmt(vals[m]["mean"] / max(v["mean"] for v in vals.values())) if m in vals else "-"
                        for m in models
                    ]
                    for env, vals in relative.items()
                ],
            ),
            "",
            "![relative error](relative_error.png)",
            "",
        ]
    missing = [
        run_name(e, m, s)
        for e in env_names
        for m in models
        for s in seeds
        if not _json_matches(out / "runs" / run_name(e, m, s) / "eval.json", {**request, "data": f"data/{e}-test.npz"})
    ]
    if missing:
        text += ["## Missing runs (not in the statistics)", ""]
        text += [f"- {m}{': ' + failed[m] if failed and m in failed else ''}" for m in missing] + [""]
    atomic_write_bytes(out / "prediction.md", "\n".join(text).encode())
    return rows


def plot_absolute(path: Path, env: str, curves: Mapping[str, tuple[Sequence[int], Mapping[int, Mapping]]]) -> None:
    """Fig. 3: mean step-wise error vs horizon per model with CI bands (log y if it spans a factor >= 10)."""
    plt = _pyplot()
    colors = model_colors(list(curves))
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    values = []
    for model, (hs, st) in curves.items():
        mean = np.array([st[h]["mean"] for h in hs])
        low, high = np.array([st[h]["ci_low"] for h in hs]), np.array([st[h]["ci_high"] for h in hs])
        n = st[hs[0]]["n"] if hs else 0
        ax.plot(hs, mean, marker="o", color=colors[model], label=f"{model} (n={n})")
        ax.fill_between(hs, low, high, color=colors[model], alpha=0.25, lw=0)
        values += [v for v in np.concatenate([mean, low, high]) if math.isfinite(v) and v > 0]
    if values and max(values) / min(values) >= 10:
        ax.set_yscale("log")
    ax.set_xlabel("prediction horizon (steps)")
    ax.set_ylabel("mean step-wise error")
    ax.set_title(f"{env}: prediction error (mean over seeds, 95 % bootstrap CI)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, _figure_bytes(fig))


def plot_relative(path: Path, relative: Mapping[str, Mapping[str, Mapping[str, float]]]) -> None:
    """Fig. 2: per env a group of bars (one per model), normalised by the env's largest mean error."""
    plt = _pyplot()
    env_list = list(relative)
    models = list(dict.fromkeys(m for vals in relative.values() for m in vals))
    colors = model_colors(models)
    width = 0.8 / max(len(models), 1)
    fig, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(env_list) + 2), 4.5))
    for j, model in enumerate(models):
        xs, heights, errs = [], [], [[], []]
        for i, env in enumerate(env_list):
            vals = relative[env]
            if model not in vals:
                continue
            finite = [v["mean"] for v in vals.values() if math.isfinite(v["mean"])]
            top = max(finite) if finite else math.nan
            s = vals[model]
            h = s["mean"] / top if math.isfinite(s["mean"]) else math.nan
            xs.append(i - 0.4 + width * (j + 0.5))
            heights.append(h)
            lo, hi = s["ci_low"] / top, s["ci_high"] / top
            errs[0].append(max(h - lo, 0.0) if math.isfinite(lo) else 0.0)
            errs[1].append(max(hi - h, 0.0) if math.isfinite(hi) else 0.0)
        ax.bar(xs, heights, width, yerr=errs, capsize=3, color=colors[model], label=model)
    ax.set_xticks(range(len(env_list)), env_list)
    ax.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax.set_ylabel("relative step-wise error (worst model = 1)")
    ax.set_title("Prediction error averaged over horizons, relative to the worst model", fontsize=10)
    ax.legend()
    fig.tight_layout()
    atomic_write_bytes(path, _figure_bytes(fig))


def summarise_openloop(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    planners: Sequence[str],
    request: Mapping[str, Any],
) -> list[dict[str, Any]]:
    """Write openloop.md, openloop.csv and openloop_ENV.png from the runs' openloop_PLANNER.json files."""
    from pets.stats import bootstrap_band, summarise

    out = Path(out)
    rows, text = (
        [],
        [
            "# Open-loop planning (GEM paper section 5.2)",
            "",
            f"Each trained model plans {request['steps']} actions once from the initial state of "
            f"{request['episodes']} episodes (seed {request['seed']}); the actions run in the real env "
            "without feedback (rewards after a real termination count as 0). Per seed: the mean over "
            "episodes; then mean over seeds with the 95 % percentile-bootstrap CI.",
            "",
        ],
    )
    plt = _pyplot()
    colors = model_colors(list(models))
    for env in env_names:
        table, panels = [], {}
        for planner in planners:
            for model in models:
                results = []
                for seed in seeds:
                    path = out / "runs" / run_name(env, model, seed) / f"openloop_{planner}.json"
                    if _json_matches(path, {**request, "planner": planner}):
                        results.append(json.loads(path.read_text()))
                if not results:
                    continue
                per_step = summarise([r["mean_reward_per_step"]["mean"] for r in results], seed=BOOT_SEED)
                total = summarise([r["total"]["mean"] for r in results], seed=BOOT_SEED)
                rows.append(
                    {
                        "env": env,
                        "planner": planner,
                        "model": model,
                        "n_seeds": per_step["n"],
                        "steps": request["steps"],
                        "reward_per_step_mean": per_step["mean"],
                        "reward_per_step_ci_low": per_step["ci_low"],
                        "reward_per_step_ci_high": per_step["ci_high"],
                        "reward_per_step_iqm": per_step["iqm"],
                        "total_mean": total["mean"],
                        "total_ci_low": total["ci_low"],
                        "total_ci_high": total["ci_high"],
                    }
                )
                table.append([planner, model, str(per_step["n"]), fmt_ci(per_step), fmt_ci(total)])
                panels.setdefault(planner, {})[model] = np.array([r["reward_per_step"]["mean"] for r in results])
        if not table:
            continue
        text += [
            f"## {env}",
            "",
            md_table(["planner", "model", "seeds", "reward per step", "total reward"], table),
            "",
            f"![open loop](openloop_{env}.png)",
            "",
        ]
        fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
        for ax, (planner, by_model) in zip(axes[0], panels.items()):
            for model, curves in by_model.items():
                steps = np.arange(1, curves.shape[1] + 1)
                low, high = bootstrap_band(curves, seed=BOOT_SEED)
                ax.plot(steps, curves.mean(axis=0), color=colors[model], label=f"{model} (n={len(curves)})")
                ax.fill_between(steps, low, high, color=colors[model], alpha=0.25, lw=0)
            ax.set_title(f"{env}, {planner}: open-loop reward per step", fontsize=10)
            ax.set_xlabel("step")
            ax.set_ylabel("reward (mean over seeds, 95 % CI)")
            ax.grid(alpha=0.3)
            ax.legend()
        fig.tight_layout()
        atomic_write_bytes(out / f"openloop_{env}.png", _figure_bytes(fig))
    write_csv(
        out / "openloop.csv",
        rows,
        [
            "env",
            "planner",
            "model",
            "n_seeds",
            "steps",
            "reward_per_step_mean",
            "reward_per_step_ci_low",
            "reward_per_step_ci_high",
            "reward_per_step_iqm",
            "total_mean",
            "total_ci_low",
            "total_ci_high",
        ],
    )
    atomic_write_bytes(out / "openloop.md", "\n".join(text).encode())
    return rows


# =========================================================================== CLI
def build_parser() -> OneLineParser:
    p = OneLineParser(
        prog=PROG,
        description="A/B comparison of dynamics heads over envs and seeds, with bootstrap "
        "statistics and plots (resumable).",
    )
    sub = p.add_subparsers(dest="mode", required=True, parser_class=OneLineParser)

    def common(q: OneLineParser) -> None:
        q.add_argument("--envs", required=True, help="comma-separated envs (catalogue names or gymnasium ids)")
        q.add_argument("--models", required=True, help="comma-separated models (pets.config.HEADS)")
        q.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
        q.add_argument("--out", type=Path, required=True, help="output directory (runs, data, summaries)")
        q.add_argument("--workers", type=int, default=1, help="parallel runs, one CPU thread each (default 1)")
        q.add_argument("--preset", default="research", help="config preset: research (default) or fast")
        q.add_argument("--device", choices=("cpu", "cuda", "auto"), default=None, help="device of every run")
        q.add_argument("--quiet", action="store_true", help="no progress bar")
        q.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for every run")

    on = sub.add_parser("online", prog=f"{PROG} online", help="online PETS runs (run_pets.py)")
    common(on)
    on.add_argument("--trials", type=int, required=True, help="trials per run")
    on.add_argument("--final-window", type=int, default=3, help="trials averaged for the final reward (default 3)")
    on.add_argument(
        "--planners",
        help="also compare these planners (comma-separated pets.config.PLANNERS); every model x planner pair is an arm",
    )

    off = sub.add_parser("offline", prog=f"{PROG} offline", help="offline training and prediction error")
    common(off)
    off.add_argument("--episodes", type=int, default=100, help="training episodes per env (default 100)")
    off.add_argument("--test-episodes", type=int, default=20, help="test episodes per env (default 20)")
    off.add_argument("--max-steps", type=int, help="steps per collected episode at most (default: env's length)")
    off.add_argument(
        "--policy",
        default="random",
        help="data policy: random (default), smooth-random[:BETA], or "
        "existing (use DIR/data/ENV-{train,test}.npz as they are)",
    )
    off.add_argument("--horizons", default="1,5,10,25,50", help="prediction horizons (default 1,5,10,25,50)")
    off.add_argument("--starts", type=int, default=1000, help="start points of the evaluation (default 1000)")
    off.add_argument("--openloop", action="store_true", help="also plan open loop with every trained model")
    off.add_argument("--planners", default="cem,mppi", help="open-loop planners (default cem,mppi)")
    off.add_argument("--openloop-steps", type=int, default=50, help="open-loop plan length (default 50)")
    off.add_argument("--openloop-episodes", type=int, default=5, help="open-loop episodes per run (default 5)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from pets.config import PRESETS

    try:
        if args.preset not in PRESETS:
            raise UsageError(f"unknown preset {args.preset!r}; accepted: {', '.join(PRESETS)}")
        env_names = parse_envs(args.envs)
        models = parse_models(args.models)
        seeds = parse_seeds(args.seeds)
        overrides = list(args.overrides)
        if args.device is not None:
            if any(o.startswith("device=") for o in overrides):
                raise UsageError("give the device once: --device or device=, not both")
        if args.mode == "online":
            if args.device is not None:
                overrides.append(f"device={args.device}")
            planners = None if args.planners is None else parse_planners(args.planners)
            result = compare_online(
                env_names,
                models,
                seeds,
                args.trials,
                args.out,
                workers=args.workers,
                preset=args.preset,
                overrides=overrides,
                final_window=args.final_window,
                progress=not args.quiet,
                planners=planners,
            )
            report = args.out / "summary.md"
        else:
            from pets.evaluate import parse_horizons

            try:
                horizons = parse_horizons(args.horizons)
            except ValueError as err:
                raise UsageError(str(err)) from None
            planners = parse_planners(args.planners)
            result = compare_offline(
                env_names,
                models,
                seeds,
                args.out,
                episodes=args.episodes,
                test_episodes=args.test_episodes,
                max_steps=args.max_steps,
                policy=args.policy,
                horizons=horizons,
                starts=args.starts,
                openloop=args.openloop,
                planners=planners,
                openloop_steps=args.openloop_steps,
                openloop_episodes=args.openloop_episodes,
                workers=args.workers,
                preset=args.preset,
                device=args.device or "auto",
                overrides=overrides,
                progress=not args.quiet,
            )
            report = args.out / "prediction.md"
    except UsageError as err:
        fail(PROG, str(err))
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; rerun the same command to continue", file=sys.stderr)
        return 130
    print(report.read_text())
    if result["failed"]:
        print(f"{PROG}: {len(result['failed'])} run(s) failed: {', '.join(sorted(result['failed']))}", file=sys.stderr)
        return EXIT_FAILED
    return 0


if __name__ == "__main__":
    sys.exit(main())
