"""The ``compare`` command line (``python -m pets.compare``, ``pets-compare``): arguments, errors, exit status.

    python -m pets.compare online  --envs E1,E2 --models M1,M2 [--seeds 0,1,2,3,4] --trials N --out DIR
                                   [--planners cem,icem] [--preset research|fast|locomotion]
                                   [--final-window W] [--device D] [--quiet] [ARMS] [BACKEND] [key=value ...]
    python -m pets.compare offline --envs E1,E2 --models M1,M2 [--seeds 0,1,2,3,4] --out DIR
                                   [--episodes E] [--test-episodes E2] [--max-steps T]
                                   [--policy random|smooth-random[:BETA]|existing] [--horizons 1,5,10,25,50]
                                   [--starts K] [--data-seeds 0,1,2]
                                   [--openloop] [--planners cem,mppi] [--openloop-steps 50] [--openloop-episodes 5]
                                   [--closedloop] [--closedloop-steps 300] [--planner-overrides KEY=VALUE,...]
                                   [--preset research|fast|locomotion] [--device D] [--quiet] [ARMS] [BACKEND]
                                   [key=value ...]
    python -m pets.compare headline [--offline S1.csv ...] [--online S2.csv ...] [--relative R1.csv ...]
                                   [--openloop O.csv ...] [--closedloop C.csv ...]
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
are never mixed; so is the directory of a run to start that is a file or holds other files (before any run).
Bad lists, envs, models or keys exit 2 with one line; a failed run is reported,
the others go on, the summary covers the finished runs, and the exit status is 3; so is a summary, table or
figure that could not be written (a full disk), in one line naming it.

The options: :mod:`pets.experiments.options`. The modes: :mod:`pets.experiments.online` and
:mod:`pets.experiments.offline`; the files they write: :mod:`pets.experiments.studies.online` and
:mod:`pets.experiments.offline_summary`.
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
    parse_planner_overrides,
    parse_planners,
    parse_seeds,
)
from pets.experiments.backend import Backend
from pets.experiments.offline import compare_offline
from pets.experiments.online import compare_online
from pets.experiments.options import build_parser
from pets.tools.cli import EXIT_FAILED, EXIT_INTERRUPTED, OneLineParser, fail, import_given, stdout_gone, write_failed


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
    from pets.presets import PRESETS

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
    if online and args.trials is None and "trials" in PRESETS.get(args.preset, {}):
        args.trials = int(PRESETS[args.preset]["trials"])  # e.g. locomotion's upper bound: the budget ends a run
    for option, key in (("envs", "env"), ("models", "head"), *((("trials", "trials"),) if online else ())):
        if getattr(args, option) is None:
            if key not in kept:
                also = " or a --preset that sets it" if option == "trials" else ""
                raise UsageError(f"--{option} is required (or {key} in a --config file{also})")
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

    if args.horizon < 1:
        fail(PROG, f"--horizon must be >= 1 (a prediction horizon of the summaries), got {args.horizon}")
    for option, path in (("--out", args.out), ("--figures", args.figures)):
        below = None if path is None else next(p for p in (path, *path.parents) if p.exists())  # what is there
        if below is not None and not below.is_dir():
            fail(
                PROG,
                f"{option} {path} is a file; give a directory"
                if below == path
                else f"{option} {path} cannot be made: {below} is a file; give a directory",
            )
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
            openloop=args.openloop,
            closedloop=args.closedloop,
            primary=args.primary,
        )
    except HeadlineError as err:
        fail(PROG, str(err))
    except ValueError as err:  # a cell that is not a number where the summary has numbers
        fail(PROG, f"a summary holds a value that is not what pets.compare writes there ({err})")
    print(text)
    return 0


def design_main(args: argparse.Namespace) -> int:
    """``pets.compare design``: each named study's registered jobs (or those left) as commands; exit 2 for a study
    without a design, or a root without committed results."""
    from pets.experiments.published import DESIGNS

    known = {design.name: design for design in DESIGNS}
    unknown = [name for name in args.studies if name not in known]
    if unknown:
        fail(PROG, f"no study named {', '.join(map(repr, unknown))} has a design; accepted: {', '.join(known)}")
    if not (args.root / "docs" / "results").is_dir():
        fail(PROG, f"{args.root} has no docs/results: run from the repository root or give --root")
    chosen = [known[name] for name in args.studies] or list(DESIGNS)
    print("\n\n".join(design.listing(args.root, args.runs, args.left) for design in chosen))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``compare`` with ``argv`` and print the report; 0, 3 (a run failed), exit 2 (bad input) or exit 3 with one
    line where a file of the command's own could not be written (a full disk: the finished runs are kept)."""
    args = _parse(build_parser(), argv)
    args.command_line = command_line(sys.argv[1:] if argv is None else argv)
    try:
        return _main(args)
    except OSError as err:  # the runs' own failures are reported per run: this is a summary, table or figure
        if isinstance(err, BrokenPipeError) and stdout_gone():
            raise  # the reader of stdout went away (`| head`): nothing of ours failed (run_command ends quietly)
        write_failed(PROG, err, "what was finished is kept: free space, then rerun the same command")


def command_line(argv: Sequence[str]) -> str:
    """The command ``argv`` (``pets.compare``'s arguments) as a shell line, as the summaries name it."""
    import shlex

    return shlex.join(["python", "-m", "pets.compare", *argv])


def _main(args: argparse.Namespace) -> int:
    """:func:`main` with the parsed arguments."""
    if args.mode == "headline":
        return headline_main(args)
    if args.mode == "report":
        from pets.experiments.regenerate import report_main

        return report_main(args)
    if args.mode == "design":
        return design_main(args)
    try:
        result, report = _run_mode(args)
    except UsageError as err:
        fail(PROG, str(err))
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; rerun the same command to continue", file=sys.stderr)
        return EXIT_INTERRUPTED
    if args.print_config:
        print_shared_config(args, result["configs"])
        return 0
    if "estimate" in result:
        print(result["estimate"])
        return 0
    print(report.read_text())
    if result["failed"]:
        print(f"{PROG}: {len(result['failed'])} run(s) failed: {', '.join(sorted(result['failed']))}", file=sys.stderr)
        return EXIT_FAILED
    return 0


def _parse(parser: OneLineParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """The parsed arguments, with ``key=value`` overrides anywhere on the line (as run_pets.py takes them), also after
    another option's value; exit 2 for anything else the parser does not know."""
    args, extra = parser.parse_known_args(argv)
    stray = [a for a in extra if a.startswith("-") or "=" not in a or not hasattr(args, "overrides")]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.overrides = [*args.overrides, *extra]
    given = [a for a in getattr(args, "overrides", []) if a.partition("=")[0].strip() == "threads"]
    if given and hasattr(args, "threads"):  # run_pets.py's spelling, threads=N, for --threads N
        from pets.config import ConfigError, parse_overrides

        line = list(sys.argv[1:] if argv is None else argv)
        if any(a == "--threads" or a.startswith("--threads=") for a in line):
            parser.error(f"give the threads once: --threads N or threads=N, not both, got {' '.join(given)}")
        try:  # threads=2 threads=2 is one value, as any key's repeat; threads=2 threads=3 is refused
            value = parse_overrides(given)["threads"]
        except ConfigError as err:
            parser.error(str(err))
        if not value.isdigit() or int(value) < 1:
            parser.error(f"threads must be a positive int (CPU threads per run), got {value!r}")
        args.threads = int(value)
        args.overrides = [a for a in args.overrides if a not in given]
    return args


def _run_mode(args: argparse.Namespace) -> tuple[dict[str, Any], Path]:
    """Check the arguments of a run mode and run it: ``(its result, the report it wrote)``; UsageError for bad
    input."""
    from pets.config import PRESETS, ConfigError

    if args.preset not in PRESETS:
        raise UsageError(f"unknown preset {args.preset!r}; accepted: {', '.join(PRESETS)}")
    overrides = overrides_from_line_and_file(args)
    try:  # before --models, --arm and --planners are looked up: a name may be registered there
        import_given(list(overrides))
    except ConfigError as err:
        raise UsageError(str(err)) from None
    estimate_only = args.estimate and not args.print_config
    if args.out is None and not (args.print_config or estimate_only):
        raise UsageError("--out is required")
    env_names = parse_envs(args.envs)
    models = parse_models(args.models)
    arms = _parse_arms(args.arm)
    models += list(arms)
    seeds = parse_seeds(args.seeds)
    out = args.out or Path(".")  # not looked at with --print-config
    _check_device(args, overrides)
    shared = {
        "env_names": env_names,
        "models": models,
        "seeds": seeds,
        "out": out,
        "backend": make_backend(args),
        "preset": args.preset,
        "overrides": overrides,
        "progress": not args.quiet,
        "arms": arms,
        "configs_only": args.print_config or (estimate_only and args.out is None),  # no --out: every run to start
    }
    if args.mode == "online":
        return _run_online(args, shared), out / "summary.md"
    return _run_offline(args, shared), out / "prediction.md"


def _parse_arms(texts: Sequence[str]) -> dict[str, tuple[str, dict[str, str]]]:
    """``{label: (model, overrides)}`` of the ``--arm`` options; UsageError for a label given twice."""
    arms = {}
    for text in texts:
        label, head, own = parse_arm(text)
        if label in arms:
            raise UsageError(f"--arm {label} is given twice")
        arms[label] = (head, own)
    return arms


def _check_device(args: argparse.Namespace, overrides: Sequence[str]) -> None:
    """UsageError for a device given twice, or CUDA asked for on a local backend where torch sees none."""
    if args.device is not None:
        if any(o.startswith("device=") for o in overrides):
            raise UsageError("give the device once: --device or device=, not both")
    device = args.device or next((o.partition("=")[2] for o in overrides if o.startswith("device=")), None)
    if device == "cuda" and args.backend == "local":
        import torch

        if not torch.cuda.is_available():
            raise UsageError("--device cuda was asked for but torch sees no CUDA device here; use --device cpu")


def _run_online(args: argparse.Namespace, shared: dict[str, Any]) -> dict[str, Any]:
    """``compare online`` with the checked arguments (``shared``: those of both modes, as keywords)."""
    if args.device is not None:
        shared["overrides"].append(f"device={args.device}")
    return compare_online(
        **shared,
        trials=args.trials,
        final_window=args.final_window,
        planners=None if args.planners is None else parse_planners(args.planners),
        until_threshold=args.until_threshold,
        estimate=args.estimate and not args.print_config,
        command=getattr(args, "command_line", None),
    )


def _run_offline(args: argparse.Namespace, shared: dict[str, Any]) -> dict[str, Any]:
    """``compare offline`` with the checked arguments (``shared``: those of both modes, as keywords)."""
    from pets.learning.evaluation import parse_horizons

    try:
        horizons = parse_horizons(args.horizons)
    except ValueError as err:
        raise UsageError(str(err)) from None
    _planning_options(args)
    planners = parse_planners(args.planners)
    return compare_offline(
        **shared,
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
        planner_overrides=parse_planner_overrides(args.planner_overrides),
        device=args.device or "auto",
        protocol=args.protocol,
        data_seeds=parse_seeds(args.data_seeds, "--data-seeds"),
        estimate=args.estimate and not args.print_config,
        command=getattr(args, "command_line", None),
    )


#: ``compare offline``'s planning options: (flag, attribute, default, the loop it sets; None: either).
_PLANNING_OPTIONS = (
    ("--planners", "planners", "cem,mppi", None),
    ("--openloop-steps", "openloop_steps", 50, "--openloop"),
    ("--openloop-episodes", "openloop_episodes", 5, None),
    ("--closedloop-steps", "closedloop_steps", 300, "--closedloop"),
)


def _planning_options(args: argparse.Namespace) -> None:
    """Set the planning options not given to their defaults; UsageError for one given without the planning it sets
    (``--planners cem`` without ``--openloop`` or ``--closedloop`` planned nothing and said nothing)."""
    asked = {"--openloop": args.openloop, "--closedloop": args.closedloop}
    for flag, attr, default, loop in _PLANNING_OPTIONS:
        if getattr(args, attr) is None:
            setattr(args, attr, default)
        elif not (asked[loop] if loop else any(asked.values())):
            loops = loop or "--openloop or --closedloop"
            raise UsageError(f"{flag} sets the planning of {loops}, not asked for: give {loops} or leave it out")
