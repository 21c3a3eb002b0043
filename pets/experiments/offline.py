"""The offline protocol: collect the data sets, then train, evaluate and open-loop plan every run that lacks it.

Per env: a training and a separate test data set with ``pets.collect`` (``DIR/data/ENV-train.npz``
with data seed 0 and E episodes, ``DIR/data/ENV-test.npz`` with data seed 1 and E2 episodes, same
policy), reused if present (an error if they were collected with another policy, seed or episode
count). With ``--data-seeds`` D > 0 also ``ENV-dD-{train,test}.npz``, collected with seeds 100 D and 100 D + 1
(SAC trained anew with 100 D): data sets as a second source of variance, runs ``ENV-MODEL-dD-sS``.
``--policy existing`` takes both files as they are (e.g. collected from a trained agent with
``pets.collect --policy run:RUN_DIR --out DIR/data/ENV-train.npz``); then the data options are unused.
``--policy sac[:STEPS]`` trains SAC for STEPS env steps (default: the protocol's training plus validation
samples, 110k for ``paper``) and keeps every transition as the training data, saves the agent as
``DIR/data/ENV-sac.zip`` and rolls it (stochastic policy) for the test episodes: the GEM paper's data.

``--protocol`` (:mod:`pets.data.protocols`): ``pets`` (default) or ``paper`` (the GEM paper's training; its test
set of 20k samples gives the default ``--test-episodes``, ceil(20000 / episode length)).

Per run: train offline (``pets.learning.offline.train_offline``, model seed = the run's seed) unless the
run directory holds a trained model; evaluate on the test data (``pets.evaluate``, mean mode, the
same start points for every model and seed of an env: evaluation seed 0; ``standardized_error`` scaled
by the training data) into ``eval.json`` unless it holds this evaluation already; with ``--openloop``,
open-loop planning (``pets.openloop``, seed 2) per planner into ``openloop_PLANNER.json``; with ``--closedloop``,
MPC with the frozen model (``pets.openloop --closed-loop``, the same episodes) into ``closedloop_PLANNER.json``.
Jobs run on the backend (:class:`pets.experiments.runner.Backend`): a pool of K processes or, with K = 1, this
process; or one Ray task each. A job killed part way is redone whole when it runs again (``config.yaml`` is
written last). The data sets: :mod:`pets.experiments.offline_data`; the run jobs: :mod:`pets.experiments.offline_jobs`.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pets.experiments.arguments import PROG, UsageError, few_seeds_warning
from pets.experiments.backend import Backend
from pets.experiments.offline_data import (
    EXISTING,
    OPENLOOP_SEED,
    check_data_paths,
    checked_data_seeds,
    collect_data,
    collect_seeds,
    data_paths,
    expected_policy_name,
    prepare_data,
    sac_agent_path,
    sac_steps,
)
from pets.experiments.offline_jobs import CLOSED, OPEN, check_run_dir, offline_job, offline_todo
from pets.experiments.offline_summary import summarise_offline
from pets.experiments.rundirs import NOT_COMPARED, check_out_writable, left_to_auto, run_name
from pets.experiments.runner import open_backend, sweep_lock
from pets.experiments.studies.planning import summarise_openloop
from pets.learning.error_metrics import own_metric_names

#: Seed of the start points of the prediction-error evaluation (the same for every model and seed).
EVAL_SEED = 0


@dataclass(frozen=True)
class _Sweep:
    """The runs of one offline comparison and the settings they share."""

    out: Path
    env_names: Sequence[str]
    models: Sequence[str]
    seeds: Sequence[int]
    data_seeds: Sequence[int]
    arms: Mapping[str, tuple[str, Mapping[str, str]]]
    extra: Mapping[str, str]
    preset: str
    protocol: str
    device: str

    def arm(self, model: str) -> tuple[str, dict[str, str]]:
        """``(head, overrides)`` of a model or ``--arm`` label: its own overrides over the shared ones."""
        head, own = self.arms.get(model, (model, {}))
        return head, {**self.extra, **own}


def compare_offline(
    env_names: Sequence[str],
    models: Sequence[str],
    seeds: Sequence[int],
    out: Path,
    *,
    episodes: int = 100,
    test_episodes: int | None = None,
    max_steps: int | None = None,
    policy: str = "random",
    horizons: Sequence[int] = (1, 5, 10, 25, 50),
    starts: int = 1000,
    openloop: bool = False,
    planners: Sequence[str] = ("cem", "mppi"),
    openloop_steps: int = 50,
    openloop_episodes: int = 5,
    closedloop: bool = False,
    closedloop_steps: int = 300,
    planner_overrides: Mapping[str, str] | None = None,
    backend: Backend | None = None,
    preset: str = "research",
    device: str = "auto",
    overrides: Sequence[str] = (),
    protocol: str = "pets",
    progress: bool = True,
    arms: Mapping[str, tuple[str, Mapping[str, str]]] | None = None,
    configs_only: bool = False,
    data_seeds: Sequence[int] = (0,),
    estimate: bool = False,
    command: str | None = None,
) -> dict[str, Any]:
    """Collect, train, evaluate (and open-loop plan) everything missing, then write the summaries.

    ``test_episodes`` None: 20, or under a protocol with a test-set size, enough episodes of the env's length.
    ``backend``: where the runs run (default: one local worker, one thread per run).
    ``arms``: ``{label: (model, overrides)}`` for the names in ``models`` that are arms (``--arm``), not models.
    ``configs_only``: return ``{"configs": {run name: resolved config}}`` once the arguments are checked, without
    looking at ``out`` or running anything (``--print-config``).
    ``estimate``: return ``{"estimate": text}``, the CPU-hours of the data sets, trainings and planning still to do
    measured on this machine (:mod:`pets.experiments.offline_estimate`), running and writing nothing
    (``--estimate``); with ``configs_only``, of all of it, ``out`` not looked at.
    ``data_seeds``: the data sets (``--data-seeds``): every model and seed is trained and evaluated on each
    (:func:`data_paths`, :func:`collect_seeds`); runs pair by (data seed, seed).
    ``planner_overrides``: ``planner.*`` settings of the open- and closed-loop planning (``--planner-overrides``),
    applied over each run's own planner config and recorded in the request, so that other settings plan anew.
    ``command``: the command line, named in prediction.md.

    Returns ``{"data": {file: collected|reused}, "todo": {run: [what was missing]}, "done": {run: [what was
    done]}, "failed": {run: message}, "summary"}``; runs absent from "todo" were reused as they were.
    """
    backend = backend or Backend()
    proto, policy, steps = _protocol_and_policy(protocol, policy)
    _check_counts(episodes, test_episodes, starts, openloop_steps, openloop_episodes, closedloop_steps, max_steps)
    expected_policy_name(policy)
    extra = _shared_overrides(overrides, backend.threads)
    out = Path(out).resolve()
    data_seeds = checked_data_seeds(data_seeds)
    sweep = _Sweep(out, env_names, models, seeds, data_seeds, arms or {}, extra, preset, protocol, device)
    configs = _expected_configs(sweep, proto, configs_only)
    _check_planner_overrides(configs, planners, planner_overrides, openloop, closedloop)
    if estimate:  # what is left to do, projected (no --out: all of it)
        from pets.experiments.offline_estimate import sweep_estimate

        data = (policy, steps, episodes, test_episodes, proto, max_steps, False, backend.threads, configs_only)
        data_jobs = _data_sets(sweep, *data)[1]
        plan = {OPEN: (openloop_steps, openloop_episodes, list(planners) * openloop),
                CLOSED: (closedloop_steps, openloop_episodes, list(planners) * closedloop)}  # fmt: skip
        requests = _requests(horizons, starts, openloop_steps, openloop_episodes, closedloop_steps, planner_overrides)
        pending = None if configs_only else _jobs(sweep, requests, plan[OPEN][2], plan[CLOSED][2])[1]
        workers = backend.workers if backend.kind == "local" else None
        text = sweep_estimate(sweep, configs, proto, data_jobs, pending, plan, planner_overrides, workers)
        return {"estimate": text}
    if configs_only:
        return {"configs": configs}
    check_data_paths(out / "data", env_names, data_seeds)
    check_out_writable(out)  # after every argument is checked: bad input leaves no directory behind
    with sweep_lock(out):  # one sweep at a time in OUT: a second command is refused, never interleaved
        requests = _requests(horizons, starts, openloop_steps, openloop_episodes, closedloop_steps, planner_overrides)
        jobs, pending = _jobs(sweep, requests, list(planners) if openloop else [], list(planners) if closedloop else [])
        total = len(env_names) * len(models) * len(seeds) * len(data_seeds)
        alone = backend.kind == "local" and backend.workers == 1  # a job's own progress bar only when it runs here
        with open_backend(backend, out, needed=bool(jobs)) as run:  # Ray: connected and checked before any work
            data_actions, data_jobs = _data_sets(
                sweep, policy, steps, episodes, test_episodes, proto, max_steps, progress and alone, backend.threads
            )
            data_failed = _run_data_jobs(run, data_jobs, data_actions, progress)
            if data_failed:  # the runs of a data set that could not be made fail with the reason; the others go on
                jobs = [job for job in jobs if (job[2][0]["env"], job[2][0]["data_seed"]) not in data_failed]
            _say_what_runs(total, (len(pending), len(jobs)), backend, data_actions, len(seeds))
            results = run(jobs, processes=True, progress=progress, desc="offline runs")
        for (env, d), message in data_failed.items():
            results |= {run_name(env, m, s, data_seed=d): (False, f"no data: {message}") for m in models for s in seeds}
        failed = {name: msg for name, (ok, msg) in results.items() if not ok}
        done = {name: res["done"] for name, (ok, res) in results.items() if ok}
        summary = summarise_offline(
            out, env_names, models, seeds, requests["eval"], failed, data_seeds=data_seeds, command=command
        )
        for kind in [OPEN] * openloop + [CLOSED] * closedloop:  # openloop.md, closedloop.md
            summarise_openloop(out, env_names, models, seeds, planners, requests[kind], kind=kind)
        return {"data": data_actions, "todo": pending, "done": done, "failed": failed, "summary": summary}


def _protocol_and_policy(protocol: str, policy: str) -> tuple[Any, str, int | None]:
    """``(the protocol, the policy, SAC's steps)``: a ``sac`` policy with its step budget made explicit
    (``sac:STEPS``), steps None for other policies; UsageError for an unknown protocol or a SAC policy without a
    budget."""
    from pets.data.protocols import get_protocol

    try:
        proto = get_protocol(protocol)
    except ValueError as err:
        raise UsageError(str(err)) from None
    steps = sac_steps(policy, protocol)
    if steps is not None:
        policy = f"sac:{steps}"
    return proto, policy, steps


def _say_what_runs(total: int, jobs: tuple[int, int], backend: Backend, data: Mapping[str, str], n_seeds: int) -> None:
    """The status line on stderr (runs reused, runs with work to do, those whose data set could not be made, the data
    files) and the few-seeds warning. ``jobs``: the runs with work to do, and of them those whose data are there."""
    no_data = f", {jobs[0] - jobs[1]} without their data set (failed)" if jobs[0] > jobs[1] else ""
    print(
        f"{PROG}: {total} runs: {total - jobs[0]} reused, {jobs[1]} with work to do{no_data} "
        f"({backend.describe()}); data: " + ", ".join(f"{k} {v}" for k, v in data.items()),
        file=sys.stderr,
    )
    warning = few_seeds_warning(n_seeds)
    if warning:
        print(warning, file=sys.stderr)


def _test_episodes(env: str, test_episodes: int | None, proto: Any, max_steps: int | None) -> int:
    """The test episodes of ``env``: ``test_episodes``, else 20, else under a protocol with a test-set size
    enough episodes of the env's length."""
    import envs

    if test_episodes is not None:
        return test_episodes
    if proto.test_samples is None:
        return 20
    return -(-proto.test_samples // (max_steps or envs.get(env).episode_length))


def _check_counts(
    episodes: int,
    test_episodes: int | None,
    starts: int,
    openloop_steps: int,
    openloop_episodes: int,
    closedloop_steps: int,
    max_steps: int | None,
) -> None:
    """UsageError for a count below 1."""
    for name, value in (
        ("episodes", episodes),
        ("test-episodes", 1 if test_episodes is None else test_episodes),
        ("starts", starts),
        ("openloop-steps", openloop_steps),
        ("openloop-episodes", openloop_episodes),
        ("closedloop-steps", closedloop_steps),
    ):
        if value < 1:
            raise UsageError(f"--{name} must be >= 1, got {value}")
    if max_steps is not None and max_steps < 1:
        raise UsageError(f"--max-steps must be >= 1, got {max_steps}")


def _shared_overrides(overrides: Sequence[str], threads: int) -> dict[str, str]:
    """The ``key=value`` overrides of every run, with the backend's threads; UsageError for a key the command sets."""
    from pets.config import ConfigError, parse_overrides

    try:
        extra = parse_overrides(list(overrides))
    except ConfigError as err:
        raise UsageError(str(err)) from None
    for key in ("seed", "head", "env", "device"):
        if key in extra:
            raise UsageError(f"{key}= is set by the command itself; do not pass it as an override")
    extra["threads"] = str(threads)
    return extra


def _expected_configs(sweep: _Sweep, proto: Any, configs_only: bool) -> dict[str, Any]:
    """{run name: the config it must have} of every (env, model, seed, data seed); UsageError for a bad config or
    (unless ``configs_only``) a run directory its job cannot use (:func:`check_run_dir`)."""
    from pets.config import ConfigError
    from pets.learning.offline import offline_config

    configs = {}
    for env in sweep.env_names:
        for model in sweep.models:
            head, overrides = sweep.arm(model)
            for seed in sweep.seeds:
                try:
                    expected = offline_config(
                        env,
                        head,
                        overrides,
                        preset=sweep.preset,
                        seed=seed,
                        device=sweep.device,
                        protocol=sweep.protocol,
                    )
                except ConfigError as err:
                    raise UsageError(str(err)) from None
                for d in sweep.data_seeds:
                    configs[run_name(env, model, seed, data_seed=d)] = expected
                    run_dir = sweep.out / "runs" / run_name(env, model, seed, data_seed=d)
                    if not configs_only:  # the searched architecture is the run's own choice
                        searched = ("model.hidden_size", "model.num_layers") if proto.architectures(env) else ()
                        ignore = (*NOT_COMPARED, *searched, *left_to_auto(overrides))
                        check_run_dir(run_dir, sweep.out, expected, ignore)
    return configs


def _check_planner_overrides(
    configs: Mapping[str, Any],
    planners: Sequence[str],
    overrides: Mapping[str, str] | None,
    openloop: bool,
    closedloop: bool,
) -> None:
    """UsageError unless ``overrides`` apply to every planning asked for, on every run's config (planner keys, valid
    values: a horizon one env's preset makes invalid is refused naming that run)."""
    from pets.config import ConfigError
    from pets.planning.openloop import planning_config

    if not overrides:
        return
    if not (openloop or closedloop):
        raise UsageError("--planner-overrides sets the planning of --openloop / --closedloop; give one of them")
    for run, cfg in configs.items():
        for planner in planners:
            for closed in [False] * openloop + [True] * closedloop:
                try:
                    planning_config(cfg, planner, 50, overrides, closed=closed)
                except ConfigError as err:
                    raise UsageError(f"--planner-overrides: {err} (run {run})") from None


def _requests(
    horizons: Sequence[int],
    starts: int,
    openloop_steps: int,
    openloop_episodes: int,
    closedloop_steps: int,
    planner_overrides: Mapping[str, str] | None = None,
) -> dict[str, dict[str, Any]]:
    """What a run's eval.json, openloop_PLANNER.json and closedloop_PLANNER.json must have been made with:
    ``{"eval", "openloop", "closedloop"}`` (the planner overrides and the error metrics of one's own only where
    given, so that results made without them still match)."""
    eval_request = {
        "horizons": sorted(set(int(h) for h in horizons)),
        "starts": starts,
        "seed": EVAL_SEED,
        "mode": "mean",
        # standardized_error is scaled by the training data's observation std (eval.json files from before
        # this key was added standardized by the test data, without the per-part errors: they are redone)
        "standardized_by": "train data",
        **({"metrics": list(own)} if (own := own_metric_names()) else {}),  # one's own (imports): redone without
    }
    planning = {"overrides": dict(planner_overrides)} if planner_overrides else {}
    openloop_request = {"steps": openloop_steps, "episodes": openloop_episodes, "seed": OPENLOOP_SEED, **planning}
    closedloop_request = {"steps": closedloop_steps, "episodes": openloop_episodes, "seed": OPENLOOP_SEED, **planning}
    return {"eval": eval_request, "openloop": openloop_request, "closedloop": closedloop_request}


def _jobs(
    sweep: _Sweep, requests: Mapping[str, Mapping[str, Any]], planners: list[str], closed_planners: list[str]
) -> tuple[list, dict[str, list[str]]]:
    """``(jobs, {run: what it lacks})`` of the runs with work to do (:func:`offline_todo`), data set by data set."""
    jobs, pending = [], {}
    for env in sweep.env_names:
        for model in sweep.models:
            for seed, d in ((seed, d) for d in sweep.data_seeds for seed in sweep.seeds):
                job = _run_job(sweep, env, model, seed, d, requests, planners, closed_planners)
                todo = offline_todo(job)
                if todo:
                    name = run_name(env, model, seed, data_seed=d)
                    jobs.append((name, offline_job, (job,)))
                    pending[name] = todo
    return jobs, pending


def _run_job(
    sweep: _Sweep,
    env: str,
    model: str,
    seed: int,
    d: int,
    requests: Mapping[str, Mapping[str, Any]],
    planners: list[str],
    closed_planners: list[str],
) -> dict[str, Any]:
    """The :func:`offline_job` of one (env, model, seed, data seed)."""
    head, overrides = sweep.arm(model)
    train_path, test_path = data_paths(sweep.out / "data", env, d)
    return {
        "env": env,
        "model": head,
        "seed": seed,
        "data_seed": d,
        "run_dir": str(sweep.out / "runs" / run_name(env, model, seed, data_seed=d)),
        "train_data": str(train_path),
        "test_data": str(test_path),
        "overrides": overrides,
        "preset": sweep.preset,
        "protocol": sweep.protocol,
        "device": sweep.device,
        "eval_request": {**requests["eval"], "data": f"data/{test_path.name}"},
        "planners": planners,
        "openloop_request": requests["openloop"],
        "closed_planners": closed_planners,
        "closedloop_request": requests["closedloop"],
    }


def _data_sets(
    sweep: _Sweep,
    policy: str,
    steps: int | None,
    episodes: int,
    test_episodes: int | None,
    proto: Any,
    max_steps: int | None,
    progress: bool,
    threads: int,
    fresh: bool = False,
) -> tuple[dict[str, str], list]:
    """``({file: "reused"}, jobs)``: every existing data file checked here, a backend job per data set that lacks
    a file (:func:`collect_data`, named "ENV data D"). UsageError for a file made with other settings. ``fresh``:
    no file looked at, every one to make (``--policy existing``: none)."""
    actions, jobs = {}, []
    for env, d in ((env, d) for env in sweep.env_names for d in sweep.data_seeds):
        missing = []
        train_path, test_path = data_paths(sweep.out / "data", env, d)
        (train_seed, test_seed), n_test = collect_seeds(d), _test_episodes(env, test_episodes, proto, max_steps)
        parts = (("train", train_path, train_seed, episodes), ("test", test_path, test_seed, n_test))
        for part, path, seed, n in parts:
            part_policy = f"sb3:{sac_agent_path(train_path)}" if steps is not None and part == "test" else policy
            if fresh and policy == EXISTING:
                continue
            if not fresh and (path.is_file() or policy == EXISTING):
                try:
                    actions[path.name] = prepare_data(path, env, part_policy, n, seed, max_steps)
                except ValueError as err:  # e.g. the SAC agent file went missing
                    raise UsageError(f"{path.name}: {err}") from None
            else:
                missing.append((str(path), part_policy, n, seed))
        if missing:
            jobs.append((f"{env} data {d}", collect_data, (env, missing, max_steps, progress, threads)))
    return actions, jobs


def _run_data_jobs(run: Any, jobs: list, actions: dict[str, str], progress: bool) -> dict[tuple[str, int], str]:
    """Run the data jobs, adding their files to ``actions``; ``{(env, data seed): why}`` of those that failed."""
    failed = {}
    for name, (ok, value) in run(jobs, processes=True, progress=progress, desc="data sets").items():
        if ok:
            actions.update({file: "collected" for file in value})
        else:
            env, _, d = name.split()
            failed[env, int(d)] = value
    return failed
