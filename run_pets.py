#!/usr/bin/env python
"""PETS with a swappable dynamics head.

    python run_pets.py --model MODEL --env halfcheetah [--trials N] [--seed S] [--device cpu|cuda|auto]
                       [--preset research|fast|locomotion] [--out DIR] [--resume DIR] [--video EVERY] [key=value ...]

MODEL (``pets.config.HEADS``): delta, gem (probabilistic ensembles, PETS), delta-det, gem2 (the GEM paper's
deterministic baseline and two-stage GEM, member predictions averaged) or delta-groupfeat (delta with GEM's
input features); docs/models.md describes each.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from pets.tools.cli import (
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    OneLineParser,
    fail,
    interrupts_deferred,
    run_command,
    stopped,
    write_failed,
)

if TYPE_CHECKING:
    from omegaconf import DictConfig

PROG = "run_pets.py"


def _fail(message: str) -> NoReturn:
    fail(PROG, message)


def build_parser() -> argparse.ArgumentParser:
    from pets.config import HEADS, PRESETS

    p = OneLineParser(
        prog=PROG,
        description="PETS model-based RL with a swappable dynamics model (delta, GEM and variants).",
        epilog="Any config key can be overridden as key=value, e.g. planner.population=200. Exit status: 0 done; "
        "2 bad input (one line, before any work: bad option or value, corrupt or mismatched checkpoint, unwritable "
        "--out, run directory in use); 3 the run failed (training diverged, no finite plan, a write failed, e.g. "
        "a full disk; completed trials are kept, --resume continues); 130 interrupted (Ctrl-C); 143 stopped by "
        "SIGTERM (completed trials are kept, --resume continues).",
    )
    p.add_argument(
        "--model",
        metavar="MODEL",
        help=f"dynamics model: {', '.join(HEADS)} (default: delta; docs/models.md), or your own, registered by a "
        "module given as imports=[MODULE]",
    )
    p.add_argument(
        "--env",
        help="environment: a catalogue name, a gymnasium id, or your own as package.module:ATTR (docs/api.md)",
    )
    p.add_argument("--trials", type=int, help="number of trials (episodes)")
    p.add_argument("--seed", type=int, help="seed for every random source")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), help="where the model and planner run")
    p.add_argument(
        "--preset",
        choices=tuple(PRESETS),
        help="research (default), fast (CPU) or locomotion (a 100k env-step budget; docs/studies/locomotion_gate.md); "
        "not with --resume",
    )
    p.add_argument("--out", type=Path, help="run directory (default: runs/ENV-MODEL-sSEED-TIME)")
    p.add_argument("--resume", type=Path, metavar="DIR", help="continue the run in DIR from its last trial")
    p.add_argument(
        "--video",
        type=int,
        metavar="EVERY",
        help="an MP4 of the real episode of every EVERY-th trial in RUN/videos (config key video_every)",
    )
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="a YAML file of config keys (any subset; --print-config writes one); flags and key=value win over it",
    )
    p.add_argument("--print-config", action="store_true", help="print the resolved config as YAML and exit")
    p.add_argument("--threads", type=int, help="torch CPU threads (config key threads; 0: torch's default)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    return p


def resume_settings(cfg: DictConfig, overrides: dict[str, str], run_dir: Path) -> None:
    """Apply what a resume may change to the run's config (in place): ``--trials N`` (run longer; not fewer than the
    trials done) and ``threads=N`` (CPU threads, which change no result); ConfigError (one line) for anything else."""
    from pets.config import ConfigError, set_value
    from pets.runs import rundir

    given = dict(overrides)
    for key in rundir.RESUMABLE_KEYS:
        if key in given:
            set_value(cfg, key, given.pop(key))
    if given:
        raise ConfigError(
            f"--resume changes only --trials and threads=N of the run's config, got {', '.join(sorted(given))}; "
            "start a new run for other settings"
        )
    if cfg.trials < 1 or cfg.threads < 0:
        raise ConfigError(f"--resume needs --trials >= 1 and threads >= 0, got {cfg.trials} and {cfg.threads}")
    done = rundir.recorded_trials(run_dir)
    if "trials" in overrides and cfg.trials < done:
        raise ConfigError(
            f"--trials {cfg.trials} is fewer than the {done} trials {run_dir} has done; a resume runs longer, "
            f"never shorter: give --trials > {done}, or none to finish the run's own count"
        )


#: The one precedence rule of a new run's settings (README, "Command line"), later wins.
PRECEDENCE = "env defaults < --preset < --config file < flags and key=value"


def config_file_notes(args: argparse.Namespace, from_file: dict[str, Any], env: str, head: str) -> list[str]:
    """What a ``--config`` file takes over from the other options, one line each (:data:`PRECEDENCE`): the values
    of an explicit ``--preset`` that the file replaces, and the env the file was written for when ``--env`` names
    another (its settings then apply to that env)."""
    if args.config is None:
        return []
    from omegaconf import OmegaConf

    from pets.config import flatten, make_config, read_config_file

    in_file = read_config_file(args.config)
    notes = []
    if args.preset is not None:
        preset = flatten(OmegaConf.to_container(make_config(env, head, args.preset)))
        taken = sorted(k for k, v in in_file.items() if k in preset and preset[k] != v and k not in ("env", "head"))
        if taken:
            shown = ", ".join(taken[:3]) + (f" and {len(taken) - 3} more" if len(taken) > 3 else "")
            notes.append(
                f"--config {args.config} replaces {len(taken)} value(s) of --preset {args.preset} ({shown}): "
                f"the file wins ({PRECEDENCE})"
            )
    written_for = from_file.get("env")
    if args.env and written_for and str(written_for) != env:
        notes.append(
            f"--config {args.config} was written for env {written_for}; its {len(in_file)} settings are used "
            f"with --env {args.env} ({PRECEDENCE})"
        )
    return notes


def start_line(run_dir: Path, args: argparse.Namespace, cfg: DictConfig) -> str:
    """The line a run starts with: its directory, preset and device (a research run on a CPU is told how long)."""
    from pets.builder import resolve_device

    device = resolve_device(cfg.device).type
    if args.resume is not None:
        return f"run directory: {run_dir} (resumed with its own config, on {device})"
    preset = args.preset or "research"
    hint = ""
    if preset == "research" and device == "cpu":
        hint = "; the PETS papers' planner, slow on a CPU: --preset fast is ~20x cheaper per step"
    return f"run directory: {run_dir} (preset {preset} on {device}{hint})"


def main(argv: list[str] | None = None) -> int:
    """The command (also the ``run-pets`` console script): a Ctrl-C before the run began is one line and 130 too."""
    try:
        return _main(argv)
    except KeyboardInterrupt:
        print(f"\n{PROG}: {stopped()} before the run began", file=sys.stderr)
        return EXIT_INTERRUPTED


def stopped_line(run_dir: Path) -> str:
    """The one line of a run stopped once it began (Ctrl-C, SIGTERM): its directory, the completed trials it keeps and
    the command that continues it."""
    from pets.runs import rundir

    done = rundir.recorded_trials(run_dir)
    kept = f"keeps its {done} completed trial{'' if done == 1 else 's'}" if done else "has completed no trial yet"
    return f"{PROG}: {stopped()}; the run in {run_dir} {kept}; continue with: python run_pets.py --resume {run_dir}"


def _main(argv: list[str] | None = None) -> int:
    with interrupts_deferred():  # Ctrl-C waits for the imports: a module half-imported breaks the run's next import
        args = build_parser().parse_intermixed_args(argv)  # imports pets.config, and with it torch
        import envs
        from envs.render import RenderingUnavailable
        from pets import loop
        from pets.config import (
            HEADS,
            ConfigError,
            config_yaml,
            load_config,
            make_config,
            overrides_with_file,
            parse_overrides,
        )
        from pets.data.rollout import EnvFailed
        from pets.imports import import_modules
        from pets.learning.trainer import TrainingDiverged
        from pets.models import UNREGISTERED
        from pets.planning.planners import PlanningFailed
        from pets.runs import rundir
        from pets.runs.fileio import DirectoryInUse, remove_if_unused, run_dir_error, writable_dir_error

    try:
        overrides = parse_overrides(args.overrides)
        model_given = "--model"
        if "model" in overrides:  # pets.compare's spelling, model=NAME, for --model NAME (model.* is the network)
            if args.model is not None:
                _fail(f"give the model once: --model {args.model} or model={overrides['model']}, not both")
            args.model, model_given = overrides.pop("model"), "model="
        for flag, key in (
            ("env", "env"),
            ("model", "head"),
            ("trials", "trials"),
            ("seed", "seed"),
            ("device", "device"),
            ("video", "video_every"),
            ("threads", "threads"),
        ):
            if getattr(args, flag) is None:
                continue
            if key in overrides:  # one setting given twice on one line: neither silently wins
                _fail(f"give {key} once: --{flag} {getattr(args, flag)} or {key}={overrides[key]}, not both")
            if flag not in ("env", "model"):  # --env and --model are make_config's own arguments
                overrides[key] = str(getattr(args, flag))
        if args.config is not None and args.resume is not None:
            _fail("--config starts a new run; --resume DIR takes the run's own config")
        overrides, from_file = overrides_with_file(args.config, overrides)  # env and head: --env, --model
        if args.resume is None:  # your own planners, models and codecs, before the env and the model are looked up
            overrides["imports"] = import_modules(overrides.get("imports", []))  # a resume: the run's own (load_config)
            if args.model is not None and args.model not in HEADS:  # checked after the imports: a model may be theirs
                given, network = f"--model {args.model}", ""
                if model_given == "model=":
                    given, network = f"model={args.model}", " (model.* keys set the network)"
                _fail(f"{given}: accepted models: {', '.join(HEADS)}{network}{UNREGISTERED}")
        if args.resume is not None:
            if args.env or args.model or args.out:
                _fail("--resume DIR takes the run's own config; do not pass --env, --model or --out with it")
            problem = run_dir_error(args.resume)
            if problem:
                _fail(problem)
            if args.preset is not None:
                _fail(f"--resume DIR takes the run's own config; --preset {args.preset} is refused with it")
            cfg = load_config(str(args.resume / rundir.CONFIG_FILE))
            resume_settings(cfg, overrides, args.resume)
            try:  # your own env by its import path: importable from here?
                envs.get(cfg.env)
            except ValueError as err:
                _fail(f"{err}; {args.resume} was started with it")
            run_dir = args.resume
        else:
            env_arg = args.env or from_file.get("env")
            if not env_arg:
                _fail(f"--env is required; accepted: {', '.join(envs.names())}")
            try:
                env_name = envs.get(env_arg).name
            except ValueError as err:
                _fail(str(err))
            head = args.model or from_file.get("head") or "delta"
            cfg = make_config(env_name, head, args.preset or "research", overrides)
            for note in config_file_notes(args, from_file, env_name, head):
                print(f"{PROG}: note: {note}", file=sys.stderr)
        if args.print_config:  # the resolved config, valid as a --config file; nothing is run or written
            print(config_yaml(cfg), end="")
            return 0
        if args.resume is None:
            from pets.builder import resolve_device

            resolve_device(cfg.device)  # a device this machine lacks: refused before the run directory is made
            run_dir = (
                args.out
                or Path("runs") / f"{envs.file_name(env_name)}-{cfg.head}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
            )
            # a run directory that holds a run is refused by loop.run under the lock: "in use" while it runs
    except ConfigError as err:
        _fail(str(err))
    created = not Path(run_dir).exists()
    problem = writable_dir_error(Path(run_dir))
    if problem:
        advice = "copy the run somewhere writable and resume the copy" if args.resume else "pick another --out"
        _fail(f"{problem}; {advice}")
    print(start_line(run_dir, args, cfg), file=sys.stderr)
    try:
        with interrupts_deferred():  # once the settings are checked: bad input is refused without its ~1.5 CPU-s
            import torch._dynamo  # noqa: F401  (the optimiser imports it when the run is built)
        rows = loop.run(cfg, Path(run_dir), resume=args.resume is not None, progress=not args.quiet)
    except (ConfigError, RenderingUnavailable) as err:  # the second: --video on a machine without headless GL
        remove_if_unused(Path(run_dir), created)
        _fail(str(err))
    except OSError as err:  # a write failed during the run (a full disk): the completed trials are kept
        if (Path(run_dir) / rundir.CONFIG_FILE).exists():
            write_failed(PROG, err, f"the trials completed before it are kept: free space, then --resume {run_dir}")
        write_failed(PROG, err, "no trial was completed; free space, then start the run again")
    except DirectoryInUse as err:
        _fail(f"{err}; wait for it to finish" + ("" if args.resume else ", or pick another --out"))
    except (TrainingDiverged, PlanningFailed, EnvFailed) as err:  # the trials completed before it stay in the run dir
        kept = f"the trials completed before it are kept in {run_dir}"
        if not (Path(run_dir) / rundir.CHECKPOINT_FILE).exists():
            kept = "no trial was completed"
        fail(PROG, f"{err}; {kept}", EXIT_FAILED)
    except KeyboardInterrupt:
        if not (Path(run_dir) / rundir.CONFIG_FILE).exists():  # before the run began: nothing to resume
            remove_if_unused(Path(run_dir), created)
            print(f"\n{PROG}: {stopped()} before the run began; nothing was written", file=sys.stderr)
        else:
            print(f"\n{stopped_line(Path(run_dir))}", file=sys.stderr)
        return EXIT_INTERRUPTED
    if rows:
        last = rows[-1]
        spent = rundir.stopped(rows, None, cfg.max_env_steps)
        budget = " (its budget, max_env_steps: --trials runs it no further)" if spent else ""
        print(
            f"done: {len(rows)} trials, {int(last['env_steps'])} env steps{budget}, "
            f"last episode reward {last['episode_reward']:.2f}; results in {run_dir}"
        )
    return 0


if __name__ == "__main__":
    run_command(PROG, main)
