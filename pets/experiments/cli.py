"""The ``compare`` command line (``python -m pets.compare``, ``pets-compare``): arguments, errors, exit status.

    python -m pets.compare online  --envs E1,E2 --models M1,M2 [--seeds 0,1,2,3,4] --trials N --out DIR
                                   [--planners cem,icem] [--preset research|fast]
                                   [--final-window W] [--device D] [--quiet] [ARMS] [BACKEND] [key=value ...]
    python -m pets.compare offline --envs E1,E2 --models M1,M2 [--seeds 0,1,2,3,4] --out DIR
                                   [--episodes E] [--test-episodes E2] [--max-steps T]
                                   [--policy random|smooth-random[:BETA]|existing] [--horizons 1,5,10,25,50]
                                   [--starts K] [--data-seeds 0,1,2]
                                   [--openloop] [--planners cem,mppi] [--openloop-steps 50] [--openloop-episodes 5]
                                   [--closedloop] [--closedloop-steps 300]
                                   [--preset research|fast] [--device D] [--quiet] [ARMS] [BACKEND]
                                   [key=value ...]
    python -m pets.compare headline [--offline S1.csv ...] [--online S2.csv ...] [--relative R1.csv ...]
                                   --out DIR [--figures DIR] [--horizon 50] [--model gem] [--caption TEXT]
    ARMS:    [--arm LABEL=MODEL[:key=value,...]] ... (more compared arms: a model with its own overrides)
    BACKEND: [--backend local] [--workers K] [--threads T]
             --backend ray [--address auto|ray://HOST:10001] [--threads T] [--max-retries R]
    CONFIG:  [--config FILE.yaml] [--print-config] (online, offline: settings every run shares; key=value wins;
             the file's env, head, trials stand for --envs, --models, --trials when not given)

Models are the names in ``pets.config.HEADS`` (read at run time); envs are catalogue names or
gymnasium ids. Seeds default to 0..4; with fewer than 5 a one-line warning goes to stderr once the
arguments are checked (fewer than 5 seeds cannot carry a claim; with 3 or fewer the bootstrap CI
is the min-max of the seeds).
Every (env, model, seed) has its run directory ``DIR/runs/ENV-MODEL-sSEED``. ``--arm LABEL=MODEL[:key=value,...]``
adds a compared arm: a model with its own overrides (e.g. the paper's single deterministic model beside its
5-member ensemble), with run directories and table rows under LABEL. ``--backend ray`` runs each run as a
Ray task (:mod:`pets.experiments.ray_backend`, docs/cluster.md); the files are the same.
Everything is resumable: rerunning a command reuses finished work and runs only what is missing.
A run directory that was made with a different config than the command asks for (other
overrides, preset, ...; the trial count aside) is an error (exit 2): results of different configs
are never mixed. Bad lists, envs, models or keys exit 2 with one line; a failed run is reported,
the others go on, the summary covers the finished runs, and the exit status is 1.

The modes: :mod:`pets.experiments.online` and :mod:`pets.experiments.offline`; the files they write:
:mod:`pets.experiments.online_summary` and :mod:`pets.experiments.offline_summary`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.arguments import (
    PROG,
    UsageError,
    parse_arm,
    parse_envs,
    parse_models,
    parse_planners,
    parse_seeds,
)
from pets.experiments.backend import BACKENDS, Backend
from pets.experiments.offline import compare_offline
from pets.experiments.online import compare_online
from pets.experiments.statistics import MIN_SEEDS
from pets.tools.cli import EXIT_FAILED, EXIT_INTERRUPTED, OneLineParser, fail

#: Seeds of a comparison unless ``--seeds`` says otherwise (the paper's 5).
DEFAULT_SEEDS = ",".join(str(s) for s in range(MIN_SEEDS))


def build_parser() -> OneLineParser:
    """The ``compare`` parser: the modes ``online`` and ``offline`` with their options."""
    p = OneLineParser(
        prog=PROG,
        description="A/B comparison of dynamics heads over envs and seeds, with statistics over seeds "
        "(rliable: IQM, stratified-bootstrap CIs, probability of improvement) and plots (resumable).",
    )
    sub = p.add_subparsers(dest="mode", required=True, parser_class=OneLineParser)

    def common(q: OneLineParser) -> None:
        # --envs, --models, --out (and online's --trials) are required unless --config gives them (main checks)
        q.add_argument("--envs", help="comma-separated envs (catalogue names, gymnasium ids or package.module:ATTR)")
        q.add_argument("--models", help="comma-separated models (pets.config.HEADS)")
        q.add_argument(
            "--arm",
            action="append",
            default=[],
            metavar="LABEL=MODEL[:key=value,...]",
            help="one more compared arm: a model with its own overrides, under LABEL (repeatable), e.g. "
            "delta-det-x1=delta-det:model.ensemble_size=1,model.num_elites=1",
        )
        q.add_argument(
            "--seeds",
            default=DEFAULT_SEEDS,
            help=f"comma-separated seeds (default {DEFAULT_SEEDS}; fewer than {MIN_SEEDS} cannot carry a claim)",
        )
        q.add_argument("--out", type=Path, help="output directory (runs, data, summaries)")
        q.add_argument(
            "--backend",
            choices=BACKENDS,
            default="local",
            help="local: a pool of --workers on this machine (default); ray: one Ray task per run (docs/cluster.md)",
        )
        q.add_argument("--workers", type=int, help="local backend: parallel runs (default 1)")
        q.add_argument("--threads", type=int, default=1, help="CPU threads per run (Ray: CPUs per task; default 1)")
        q.add_argument(
            "--address",
            help="ray backend: the cluster (auto, or ray://HOST:10001); default: a new Ray instance on this machine",
        )
        q.add_argument(
            "--max-retries",
            type=int,
            default=3,
            help="ray backend: retries of a run whose worker or node died (default 3; it resumes its checkpoint)",
        )
        q.add_argument("--preset", default="research", help="config preset: research (default) or fast")
        q.add_argument("--device", choices=("cpu", "cuda", "auto"), default=None, help="device of every run")
        q.add_argument("--quiet", action="store_true", help="no progress bar")
        q.add_argument(
            "--config",
            type=Path,
            metavar="FILE",
            help="a YAML file of config keys for every run (any subset; --print-config writes one); its env, head "
            "and trials stand for --envs, --models and --trials when those are not given; options and key=value "
            "win over it",
        )
        q.add_argument(
            "--print-config",
            action="store_true",
            help="print the settings every run shares, resolved, as YAML (valid as --config) and exit",
        )
        q.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for every run")

    on = sub.add_parser("online", prog=f"{PROG} online", help="online PETS runs (run_pets.py)")
    common(on)
    on.add_argument("--trials", type=int, help="trials per run (required unless --config gives trials)")
    on.add_argument("--final-window", type=int, default=3, help="trials averaged for the final reward (default 3)")
    on.add_argument(
        "--until-threshold",
        action="store_true",
        help="stop each run at its first trial reaching the env's threshold (pets.experiments.online_summary."
        "THRESHOLDS); --trials is then the most",
    )
    on.add_argument(
        "--planners",
        help="also compare these planners (comma-separated pets.config.PLANNERS); every model x planner pair is an arm",
    )

    off = sub.add_parser("offline", prog=f"{PROG} offline", help="offline training and prediction error")
    common(off)
    off.add_argument("--episodes", type=int, default=100, help="training episodes per env (default 100)")
    off.add_argument(
        "--test-episodes",
        type=int,
        help="test episodes per env (default 20; --protocol paper: 20k samples' worth, ceil(20000 / episode length))",
    )
    off.add_argument("--max-steps", type=int, help="steps per collected episode at most (default: env's length)")
    off.add_argument(
        "--data-seeds",
        default="0",
        help="data sets (comma-separated ints >= 0, default 0): each is collected anew (SAC too) with its own test "
        "set, every model and seed runs on each, and the statistics pair by (data seed, seed), data sets as the "
        "outer level of the bootstrap",
    )
    off.add_argument(
        "--policy",
        default="random",
        help="data policy: random (default), smooth-random[:BETA], sac[:STEPS] (SAC's training transitions; "
        "its agent rolls the test episodes; default STEPS: the protocol's train + validation samples), or "
        "existing (use DIR/data/ENV-{train,test}.npz as they are)",
    )
    off.add_argument(
        "--protocol",
        choices=("pets", "paper"),
        default="pets",
        help="training protocol: pets (bootstrap ensemble, early stopping; default) or paper (the GEM paper's: "
        "100k/10k split, Adam 5e-4, batch 10, 10k iterations, hidden-layer search; pets.data.protocols)",
    )
    off.add_argument("--horizons", default="1,5,10,25,50", help="prediction horizons (default 1,5,10,25,50)")
    off.add_argument("--starts", type=int, default=1000, help="start points of the evaluation (default 1000)")
    off.add_argument("--openloop", action="store_true", help="also plan open loop with every trained model")
    off.add_argument("--planners", default="cem,mppi", help="open-loop planners (default cem,mppi)")
    off.add_argument("--openloop-steps", type=int, default=50, help="open-loop plan length (default 50)")
    off.add_argument("--openloop-episodes", type=int, default=5, help="open-loop episodes per run (default 5)")
    off.add_argument(
        "--closedloop",
        action="store_true",
        help="also drive MPC with every trained model, frozen (the run's planner per --planners, the open-loop "
        "episodes' seeds; closedloop.csv, paired to delta)",
    )
    off.add_argument("--closedloop-steps", type=int, default=300, help="closed-loop steps per episode (default 300)")

    head = sub.add_parser(
        "headline",
        prog=f"{PROG} headline",
        help="the per-env answer (each model against delta) from summary.csv files of earlier comparisons",
    )
    head.add_argument("--offline", type=Path, nargs="*", default=[], help="offline summary.csv files")
    head.add_argument("--online", type=Path, nargs="*", default=[], help="online summary.csv files")
    head.add_argument(
        "--relative", type=Path, nargs="*", default=[], help="offline relative_error.csv files (Fig. 2 across envs)"
    )
    head.add_argument("--horizon", type=int, default=50, help="offline horizon (default 50; else the longest below)")
    head.add_argument("--model", default="gem", help="the model whose ratio to delta is plotted (default gem)")
    head.add_argument("--caption", default="", help="a line under the figure, e.g. the machine the runs came from")
    head.add_argument("--out", type=Path, required=True, help="output directory (headline.md, the CSVs)")
    head.add_argument("--figures", type=Path, help="directory of the figures (default: --out)")
    return p


def make_backend(args: argparse.Namespace) -> Backend:
    """The :class:`Backend` of the parsed arguments; UsageError for options of the other backend."""
    if args.backend == "ray" and args.workers is not None:
        raise UsageError(
            "--workers is for --backend local; Ray runs as many runs at once as the cluster has CPUs for "
            "(--threads each)"
        )
    if args.backend == "local" and args.max_retries != 3:
        raise UsageError("--max-retries is for --backend ray")
    return Backend(
        kind=args.backend,
        workers=1 if args.workers is None else args.workers,
        threads=args.threads,
        address=args.address,
        gpus=1.0 if args.backend == "ray" and args.device == "cuda" else 0.0,
        max_retries=args.max_retries,
    )


#: Per-run settings pets.compare makes itself (--seeds, --threads, --until-threshold): a config file's are not used.
NOT_FROM_FILE = ("seed", "threads", "stop_reward")


def overrides_from_line_and_file(args: argparse.Namespace) -> list[str]:
    """The ``key=value`` overrides of every run: ``--config FILE``'s keys, then the line's (which win). The file's
    ``env``, ``head``, ``trials`` (online) and ``device`` stand for ``--envs``, ``--models``, ``--trials`` and
    ``--device`` where those are not given (set on ``args``); a note names the :data:`NOT_FROM_FILE` keys it sets
    away from their defaults. UsageError (one line) for a bad file or a missing required option."""
    from omegaconf import OmegaConf

    from pets.config import Config, ConfigError, override_text, overrides_with_file, parse_overrides

    online = args.mode == "online"
    aside = ("env", "head", "device", *NOT_FROM_FILE, *(("trials",) if online else ()))
    if online and args.planners is not None:
        aside += ("planner.name",)  # --planners wins over the file's planner
    try:
        line = parse_overrides(list(args.overrides))
        merged, kept = overrides_with_file(args.config, line, aside)
    except ConfigError as err:
        raise UsageError(str(err)) from None
    if "device" in kept and args.device is None and "device" not in line:
        if kept["device"] not in ("cpu", "cuda", "auto"):
            raise UsageError(f"--config {args.config}: device must be cpu, cuda or auto, got {kept['device']!r}")
        args.device = kept["device"]
    if online and args.trials is None and "trials" in kept:
        args.trials = int(kept["trials"])
    for option, key in (("envs", "env"), ("models", "head"), *((("trials", "trials"),) if online else ())):
        if getattr(args, option) is None:
            if key not in kept:
                raise UsageError(f"--{option} is required (or {key} in a --config file)")
            if option != "trials":
                setattr(args, option, str(kept[key]))
    defaults = OmegaConf.structured(Config)
    unused = [k for k in NOT_FROM_FILE if k in kept and kept[k] != defaults[k]]
    if unused:
        print(
            f"{PROG}: note: --config {args.config}: {', '.join(f'{k}: {kept[k]}' for k in unused)} not used; every "
            "run's seed, threads and stop_reward come from --seeds, --threads and --until-threshold",
            file=sys.stderr,
        )
    return [override_text(k, v) for k, v in merged.items()]


def print_shared_config(args: argparse.Namespace, configs: Mapping[str, Any]) -> None:
    """``--print-config``: the settings every run shares, resolved, as YAML valid as ``--config``; a comment
    names the keys that differ between runs (set per env and arm: pass the same options with the file)."""
    from pets.config import config_yaml, shared_config

    drop = (*NOT_FROM_FILE, *(("planner.name",) if args.mode == "online" and args.planners else ()))
    same, differ = shared_config(configs.values(), drop)
    print(f"# {PROG} {args.mode}: the settings all {len(configs)} runs share (--print-config)")
    if differ:
        print(f"# per run (not here; pass the same --envs, --models, --arm, --planners, --preset): {', '.join(differ)}")
    print(config_yaml(same), end="")


def headline_main(args: argparse.Namespace) -> int:
    """``compare headline``: print headline.md; exit 2 with one line on a bad summary file."""
    from pets.experiments.headline import HeadlineError, write_headline

    try:
        text = write_headline(
            args.offline,
            args.online,
            args.out,
            horizon=args.horizon,
            model=args.model,
            caption=args.caption,
            relative=args.relative,
            figures=args.figures,
        )
    except HeadlineError as err:
        fail(PROG, str(err))
    print(text)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``compare`` with ``argv`` and print the report; 0, 1 (a run failed) or exit 2 (bad input)."""
    parser = build_parser()
    # key=value overrides anywhere on the line (as run_pets.py takes them), also after another option's value
    args, extra = parser.parse_known_args(argv)
    stray = [a for a in extra if a.startswith("-") or "=" not in a or not hasattr(args, "overrides")]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.overrides = [*args.overrides, *extra]
    if args.mode == "headline":
        return headline_main(args)
    from pets.config import PRESETS

    try:
        if args.preset not in PRESETS:
            raise UsageError(f"unknown preset {args.preset!r}; accepted: {', '.join(PRESETS)}")
        overrides = overrides_from_line_and_file(args)
        if args.out is None and not args.print_config:
            raise UsageError("--out is required")
        env_names = parse_envs(args.envs)
        models = parse_models(args.models)
        arms = {}
        for text in args.arm:
            label, head, own = parse_arm(text)
            if label in arms:
                raise UsageError(f"--arm {label} is given twice")
            arms[label] = (head, own)
        models += list(arms)
        seeds = parse_seeds(args.seeds)
        out = args.out or Path(".")  # not looked at with --print-config
        if args.device is not None:
            if any(o.startswith("device=") for o in overrides):
                raise UsageError("give the device once: --device or device=, not both")
        device = args.device or next((o.partition("=")[2] for o in overrides if o.startswith("device=")), None)
        if device == "cuda" and args.backend == "local":
            import torch

            if not torch.cuda.is_available():
                raise UsageError("--device cuda was asked for but torch sees no CUDA device here; use --device cpu")
        backend = make_backend(args)
        if args.mode == "online":
            if args.device is not None:
                overrides.append(f"device={args.device}")
            planners = None if args.planners is None else parse_planners(args.planners)
            result = compare_online(
                env_names,
                models,
                seeds,
                args.trials,
                out,
                backend=backend,
                preset=args.preset,
                overrides=overrides,
                final_window=args.final_window,
                progress=not args.quiet,
                planners=planners,
                arms=arms,
                until_threshold=args.until_threshold,
                configs_only=args.print_config,
            )
            report = out / "summary.md"
        else:
            from pets.learning.evaluation import parse_horizons

            try:
                horizons = parse_horizons(args.horizons)
            except ValueError as err:
                raise UsageError(str(err)) from None
            planners = parse_planners(args.planners)
            result = compare_offline(
                env_names,
                models,
                seeds,
                out,
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
                closedloop=args.closedloop,
                closedloop_steps=args.closedloop_steps,
                backend=backend,
                preset=args.preset,
                device=args.device or "auto",
                overrides=overrides,
                protocol=args.protocol,
                progress=not args.quiet,
                arms=arms,
                configs_only=args.print_config,
                data_seeds=parse_seeds(args.data_seeds, "--data-seeds"),
            )
            report = out / "prediction.md"
    except UsageError as err:
        fail(PROG, str(err))
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; rerun the same command to continue", file=sys.stderr)
        return EXIT_INTERRUPTED
    if args.print_config:
        print_shared_config(args, result["configs"])
        return 0
    print(report.read_text())
    if result["failed"]:
        print(f"{PROG}: {len(result['failed'])} run(s) failed: {', '.join(sorted(result['failed']))}", file=sys.stderr)
        return EXIT_FAILED
    return 0
