"""The online protocol: start, resume or reuse every (env, arm, seed) run of run_pets.py, then summarise.

Per run: reuse it if ``metrics.csv`` has at least N rows, resume it (``run_pets.py --resume DIR
--trials N``) if it has fewer, start it (``run_pets.py --env --model --seed --trials N --out DIR
--preset P threads=T key=value ...``) if it does not exist; a job decides between starting and resuming when it
runs, so a retried job (Ray) resumes what its lost attempt began. Runs go to the backend
(:class:`pets.experiments.runner.Backend`: a pool of K local subprocesses, or one Ray task each), T torch
threads each (``--threads``, default 1; ``OMP_NUM_THREADS=T``); their output goes to
``DIR/logs/ENV-MODEL-sSEED.log``. Only the first N trials of a run enter the summary. A user
``threads=`` override is ignored (``--threads`` sets it).

``--until-threshold`` runs each run to a threshold: ``stop_reward=`` the env's :data:`THRESHOLDS` entry, so a run
stops after its first trial that reaches it (at most N trials) and counts as complete from then on; the summary's
time-to-threshold columns are then the answer, and its final / AUC columns cover the trials up to the stop.

``--planners P1,P2`` makes the planner a second axis: every (model, planner) pair is an arm with
its runs in ``DIR/runs/ENV-MODEL-PLANNER-sSEED`` (``planner.name=P`` for the run), and the tables
and plots show ``MODEL+PLANNER``; the run made without ``--planners`` (``ENV-MODEL-sSEED``) is the arm's where that
directory is absent and it ran the planner (:func:`pets.experiments.rundirs.arm_run_dir`). Wall-clock figures
compare fairly only between runs that shared the machine alike (one worker per core, no other load).
"""

from __future__ import annotations

import itertools
import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.arguments import PROG, UsageError, few_seeds_warning
from pets.experiments.backend import Backend
from pets.experiments.rundirs import (
    NOT_COMPARED,
    arm_run_dir,
    check_new_run_dir,
    check_out_writable,
    check_same_config,
    left_to_auto,
    online_arms,
    run_name,
)
from pets.experiments.runner import online_job, open_backend, sweep_lock
from pets.experiments.studies.online import THRESHOLDS, online_rows, summarise_online
from pets.runs.rundir import read_divergence, stopped


def online_plan(run_dir: Path, trials: int, stop_reward: float | None = None, max_env_steps: int | None = None) -> str:
    """``reuse`` (>= trials rows, a trial at ``stop_reward`` or the budget ``max_env_steps`` reached, or a run that
    stopped diverged: the same seed and config diverge again), ``resume`` (a run with fewer rows) or ``start`` (no
    run yet)."""
    if not (run_dir / "config.yaml").is_file():
        return "start"
    rows = online_rows(run_dir)
    done = len(rows) >= trials or stopped(rows, stop_reward, max_env_steps) or read_divergence(run_dir) is not None
    return "reuse" if done else "resume"


def start_arguments(
    run_dir: Path, env: str, model: str, seed: int, trials: int, preset: str, overrides: Sequence[str], threads: int
) -> list[str]:
    """``run_pets.py``'s arguments that start one run (:func:`pets.experiments.runner.online_job` resumes it)."""
    return [
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
        f"threads={threads}",
    ]


def compare_online(
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    trials: int,
    out: Path,
    *,
    backend: Backend | None = None,
    preset: str = "research",
    overrides: Sequence[str] = (),
    final_window: int = 3,
    progress: bool = True,
    planners: Sequence[str] | None = None,
    arms: Mapping[str, tuple[str, Mapping[str, str]]] | None = None,
    until_threshold: bool = False,
    configs_only: bool = False,
    estimate: bool = False,
    command: str | None = None,
) -> dict[str, Any]:
    """Run (or reuse/resume) every online run, then write the summary. Returns ``{"actions", "failed",
    "summary"}``. UsageError for bad settings or a run directory with another config.

    ``planners``: also compare these planners (``planner.name``); every (model, planner) pair is an arm.
    ``backend``: where the runs run (default: one local worker, one thread per run).
    ``arms``: ``{label: (model, overrides)}`` for the names in ``models`` that are arms (``--arm``), not models.
    ``until_threshold``: stop every run at its env's threshold (module docstring).
    ``configs_only``: return ``{"configs": {run name: resolved config}}`` once the arguments are checked, without
    looking at ``out`` or running anything (``--print-config``).
    ``estimate``: return ``{"estimate": text}``, the CPU-hours of the runs still to do measured on this machine
    (:mod:`pets.experiments.estimate`), without running or writing anything (``--estimate``); with
    ``configs_only``, of every run, ``out`` not looked at. ``command``: the command line, named in summary.md.
    """
    backend = backend or Backend()
    if trials < 1 or final_window < 1:
        raise UsageError(f"--trials and --final-window must be >= 1, got {trials}, {final_window}")
    extra = _shared_overrides(overrides, planners)
    _check_thresholds(env_names, until_threshold)
    out = Path(out).resolve()
    jobs, actions, configs = _plan_runs(
        out, env_names, models, seeds, trials, planners, arms, extra, preset, backend.threads, until_threshold,
        configs_only,
    )  # fmt: skip
    if estimate:  # with configs_only (no --out) every run counts as one to start
        from pets.experiments.estimate import estimate as projected

        return {"estimate": projected(configs, actions, out, backend.workers if backend.kind == "local" else None)}
    if configs_only:
        return {"configs": configs}
    if backend.kind == "local":  # Ray's nodes check their own memory, run by run
        _check_memory(configs, actions, backend.workers)
    check_out_writable(out)  # after every argument is checked: bad input leaves no directory behind
    with sweep_lock(out):  # one sweep at a time in OUT: a second command is refused, never interleaved
        counts = {a: sum(1 for v in actions.values() if v == a) for a in ("reuse", "resume", "start")}
        with open_backend(backend, out, needed=bool(jobs)) as run:
            print(
                f"{PROG}: {len(actions)} runs: {counts['reuse']} reused, {counts['resume']} to resume, "
                f"{counts['start']} to start ({backend.describe()})",
                file=sys.stderr,
            )
            warning = few_seeds_warning(len(seeds))
            if warning:
                print(warning, file=sys.stderr)
            results = run(jobs, processes=False, progress=progress, desc="online runs")
        # A run that stopped diverged is an outcome (counted as the worst), not a failure to rerun.
        failed = {n: msg for n, (ok, msg) in results.items() if not ok and not read_divergence(out / "runs" / n)}
        summary = summarise_online(
            out, env_names, models, seeds, trials, final_window, failed, planners, until_threshold=until_threshold,
            command=command,
        )  # fmt: skip
        return {"actions": actions, "failed": failed, "summary": summary}


def _shared_overrides(overrides: Sequence[str], planners: Sequence[str] | None) -> dict[str, str]:
    """The ``key=value`` overrides of every run, without ``threads`` (the backend's); UsageError for a key the
    command sets itself."""
    from pets.config import ConfigError, parse_overrides

    try:
        extra = parse_overrides(list(overrides))
    except ConfigError as err:
        raise UsageError(str(err)) from None
    extra.pop("threads", None)  # every run uses the backend's threads
    for key, option in (("trials", "--trials"), ("seed", "--seeds"), ("head", "--models"), ("env", "--envs")):
        if key in extra:
            raise UsageError(f"{key}= is set by the command itself ({option}); do not pass it as an override")
    if planners is not None and "planner.name" in extra:
        raise UsageError("give the planner once: --planners or planner.name=, not both")
    if "stop_reward" in extra:
        raise UsageError(
            "stop_reward= is set by --until-threshold (the env's threshold); do not pass it as an override"
        )
    return extra


def _check_thresholds(env_names: Sequence[str], until_threshold: bool) -> None:
    """UsageError if ``--until-threshold`` is asked for an env without a threshold."""
    unknown = [env for env in env_names if env not in THRESHOLDS] if until_threshold else []
    if unknown:
        raise UsageError(
            f"--until-threshold: no threshold for {', '.join(unknown)}; thresholds exist for "
            f"{', '.join(THRESHOLDS)} (pets.experiments.studies.online.THRESHOLDS)"
        )


def _plan_runs(
    out: Path,
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    trials: int,
    planners: Sequence[str] | None,
    arms: Mapping[str, tuple[str, Mapping[str, str]]] | None,
    extra: Mapping[str, str],
    preset: str,
    threads: int,
    until_threshold: bool,
    configs_only: bool,
) -> tuple[list, dict[str, str], dict[str, Any]]:
    """``(jobs, {run: reuse|resume|start}, {run: config})`` of every (env, arm, seed), seed-major; with
    ``configs_only`` only the configs. UsageError for a bad config or a run directory made with another one."""
    from pets.config import ConfigError, make_config

    jobs, actions, configs = [], {}, {}
    for env in env_names:
        stop = {"stop_reward": THRESHOLDS[env]} if until_threshold else {}
        # Seed-major: every arm of the first seed, then of the next, so that a sweep cut short is still paired.
        for seed, (model, planner) in itertools.product(seeds, online_arms(models, planners)):
            head, own = (arms or {}).get(model, (model, {}))
            arm_extra = {**extra, **own, **stop, **({} if planner is None else {"planner.name": planner})}
            run_dir = out / "runs" / run_name(env, model, seed, planner)
            if not configs_only:  # the arm's run made without --planners is this run (reused, or refused if it differs)
                run_dir = arm_run_dir(out / "runs", env, model, seed, planner)
            name = run_dir.name
            try:
                expected = make_config(
                    env, head, preset, {**arm_extra, "seed": seed, "trials": trials, "threads": threads}
                )
            except ConfigError as err:
                raise UsageError(str(err)) from None
            configs[name] = expected
            if configs_only:
                continue
            actions[name] = action = _checked_action(run_dir, trials, expected, arm_extra)
            if action != "reuse":
                arm_list = [f"{k}={v}" for k, v in arm_extra.items()]
                args = start_arguments(run_dir, env, head, seed, trials, preset, arm_list, threads)
                log = str(out / "logs" / f"{name}.log")
                jobs.append((name, online_job, (str(run_dir), args, trials, log, threads)))
    return jobs, actions, configs


def _check_memory(configs: Mapping[str, Any], actions: Mapping[str, str], workers: int) -> None:
    """UsageError (one line) before any run starts where the largest run to do, beside the next ``workers - 1``
    largest (those that can run with it), would not fit in this machine's free memory; CPU runs only (a GPU's free
    memory is not read from this process: each run checks itself when it starts)."""
    import envs
    from pets.builder import check_memory, resolve_device
    from pets.config import ConfigError
    from pets.limits import memory_needs

    todo = [n for n, a in actions.items() if a != "reuse" and str(resolve_device(configs[n].device)) == "cpu"]
    specs = {n: envs.get(configs[n].env) for n in todo}
    need = {
        n: sum(x.bytes for x in memory_needs(configs[n], specs[n].obs_dim, specs[n].act_dim, specs[n].episode_length))
        for n in todo
    }
    largest = sorted(todo, key=need.__getitem__, reverse=True)[: max(workers, 1)]
    if largest:
        try:
            check_memory(
                configs[largest[0]], specs[largest[0]], beside=(len(largest) - 1, sum(map(need.get, largest[1:])))
            )
        except ConfigError as err:
            raise UsageError(f"{largest[0]}: {err}") from None


def _checked_action(run_dir: Path, trials: int, expected: Any, arm_extra: Mapping[str, str]) -> str:
    """:func:`online_plan` of a run; UsageError if its directory holds another config or an offline run, or, for a
    run to start, is a file (or ``OUT/runs`` is) or holds other files: refused before any run starts, not failed as
    the run starts."""
    action = online_plan(run_dir, trials, expected.stop_reward, expected.max_env_steps)
    if action == "start":
        check_new_run_dir(run_dir)
    else:
        check_same_config(run_dir, expected, ignore=(*NOT_COMPARED, *left_to_auto(arm_extra)))
        if any(math.isnan(r["trial"]) for r in online_rows(run_dir)):
            raise UsageError(
                f"{run_dir} is an offline training run (pets.train), not an online run; "
                "use separate --out directories for online and offline comparisons"
            )
    return action
