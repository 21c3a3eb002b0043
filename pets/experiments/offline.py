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
written last).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.arguments import PROG, UsageError, few_seeds_warning
from pets.experiments.backend import Backend
from pets.experiments.offline_summary import summarise_offline
from pets.experiments.planning_summary import summarise_openloop
from pets.experiments.rundirs import (
    NOT_COMPARED,
    check_out_writable,
    check_same_config,
    json_matches,
    left_to_auto,
    run_name,
)
from pets.experiments.runner import open_backend
from pets.runs.fileio import atomic_write_bytes

#: Data seeds of the offline mode: training data, test data, open-loop initial states.
TRAIN_DATA_SEED, TEST_DATA_SEED, OPENLOOP_SEED = 0, 1, 2
#: Data set D > 0 (``--data-seeds``) collects with seeds ``D * DATA_SEED_STRIDE + TRAIN_DATA_SEED / TEST_DATA_SEED``
#: (SAC trained with the training seed), so that no two data sets share a random stream.
DATA_SEED_STRIDE = 100
#: Seed of the start points of the prediction-error evaluation (the same for every model and seed).
EVAL_SEED = 0
#: ``--policy`` value that uses the data files already in DIR/data as they are.
EXISTING = "existing"


def data_paths(data_dir: Path, env: str, data_seed: int = 0) -> tuple[Path, Path]:
    """The training and test files of one data set: ``ENV-{train,test}.npz`` (data set 0), else
    ``ENV-dD-{train,test}.npz``."""
    stem = f"{env}-d{data_seed}" if data_seed else env
    return data_dir / f"{stem}-train.npz", data_dir / f"{stem}-test.npz"


def collect_seeds(data_seed: int = 0) -> tuple[int, int]:
    """The collection seeds (training, test) of data set ``data_seed``."""
    return data_seed * DATA_SEED_STRIDE + TRAIN_DATA_SEED, data_seed * DATA_SEED_STRIDE + TEST_DATA_SEED


def sac_agent_path(train_path: Path) -> Path:
    """Where the SAC agent of a training data file lives: ``ENV[-dD]-sac.zip`` beside it."""
    return train_path.with_name(train_path.name.replace("-train.npz", "-sac.zip"))


def sac_steps(policy: str, protocol: str) -> int | None:
    """The SAC budget of a ``sac[:STEPS]`` ``--policy`` (None for other policies); UsageError if it has none."""
    from pets.data.protocols import get_protocol

    if policy != "sac" and not policy.startswith("sac:"):
        return None
    if policy == "sac":
        proto = get_protocol(protocol)
        if proto.train_samples is None:
            raise UsageError(f"--policy sac needs a step budget with --protocol {protocol}: give sac:STEPS")
        return proto.train_samples + (proto.val_samples or 0)
    from pets.data.collect import parse_policy

    try:
        return parse_policy(policy)[1]
    except ValueError as err:
        raise UsageError(str(err)) from None


def expected_policy_name(policy: str) -> str:
    """The ``policy`` name ``pets.collect`` stores for a ``--policy`` string (random, smooth-random or sac:STEPS)."""
    from pets.data.collect import DEFAULT_BETA, parse_policy

    if policy == EXISTING or policy.startswith("sac:"):
        return policy

    try:
        kind, arg = parse_policy(policy)
    except ValueError as err:
        raise UsageError(str(err)) from None
    if kind == "sb3":
        return f"sb3:{arg.name}"
    if kind == "run":
        raise UsageError(
            "--policy must be random, smooth-random[:BETA], sac[:STEPS] or existing (one policy for every env; "
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
    from pets.data.collect import collect
    from pets.data.datasets import load_dataset, save_dataset

    want = {"env": env, "policy": expected_policy_name(policy), "seed": seed, "episodes": episodes}
    if policy.startswith("sac:"):  # SAC's episodes are as many as its steps made
        del want["episodes"]
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
            "episodes": int(len(data["lengths"])),
            "policy": str(data["policy"]) if "policy" in data else None,
            "seed": int(data["seed"]) if "seed" in data else None,
        }
        got = {k: v for k, v in got.items() if k in want}
        if max_steps is not None and int(data["lengths"].max()) > max_steps:
            got["max_steps"], want["max_steps"] = int(data["lengths"].max()), max_steps
        if got != want:
            diff = "; ".join(f"{k}: {got.get(k)!r} != {want.get(k)!r}" for k in want if got.get(k) != want.get(k))
            raise UsageError(
                f"{path} was collected with other settings ({diff}); pass the same settings, "
                "delete the file or pick another --out"
            )
        return "reused"
    spec = envs.get(env)
    if policy.startswith("sac:"):
        from pets.data.collect import collect_sac
        from pets.data.sb3 import agent_bytes
        from pets.runs.fileio import atomic_write_bytes

        data, agent = collect_sac(spec, sac_steps(policy, "pets"), seed, max_steps, device="cpu", progress=progress)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(sac_agent_path(path), agent_bytes(agent))  # before the data: it needs it
        save_dataset(path, data)
        return "collected"
    save_dataset(path, collect(spec, policy, episodes, seed, max_steps, progress=progress))
    return "collected"


def collect_data(
    env: str, parts: Sequence[tuple[str, str, int, int]], max_steps: int | None, progress: bool, threads: int = 1
) -> list:
    """Collect an env's missing data files ``(path, policy, episodes, seed)`` in order (SAC's test data needs the
    agent its training data saved) with ``threads`` torch threads; the files' names. A job of the backend."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for path, policy, episodes, seed in parts:
            prepare_data(Path(path), env, policy, episodes, seed, max_steps, progress)
    finally:
        torch.set_num_threads(before)
    return [Path(path).name for path, *_ in parts]


def offline_job(job: Mapping[str, Any]) -> dict[str, Any]:
    """One (env, model, seed): train if needed, evaluate if needed, open-loop plan if asked and needed.

    Runs in a worker process (or in this one); returns what it did, ``{"name", "done": [...]}``.
    """
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(int(job["overrides"].get("threads", 1)))
    try:
        return _offline_job(job)
    finally:
        torch.set_num_threads(threads)


def _offline_job(job: Mapping[str, Any]) -> dict[str, Any]:
    from pets.config import load_config
    from pets.learning.evaluation import evaluate, write_events
    from pets.learning.offline import train_offline
    from pets.planning.openloop import open_loop

    run_dir, done = Path(job["run_dir"]), []
    if not (run_dir / "config.yaml").is_file():
        train_offline(
            job["train_data"],
            job["model"],
            run_dir,
            job["overrides"],
            preset=job["preset"],
            protocol=job["protocol"],
            seed=job["seed"],
            device=job["device"],
        )
        done.append("train")
    eval_path, request = run_dir / "eval.json", job["eval_request"]
    if "train" in done or not json_matches(eval_path, request):
        result = evaluate(
            run_dir,
            job["test_data"],
            request["horizons"],
            request["starts"],
            seed=request["seed"],
            mode=request["mode"],
            device=job["device"],
            log=lambda message: None,
            train_data=job["train_data"],
        )
        result["request"] = request
        atomic_write_bytes(eval_path, (json.dumps(result) + "\n").encode())
        if load_config(
            str(run_dir / "config.yaml")
        ).tensorboard:  # per-horizon errors for TensorBoard (pets.runs.tblog)
            write_events(run_dir, job["test_data"], result)
        done.append("eval")
    for kind, planner in _planning_tasks(job):
        path = run_dir / f"{kind}_{planner}.json"
        request = {**job[f"{kind}_request"], "planner": planner}
        if "train" in done or not json_matches(path, request):
            r = request
            result = open_loop(
                run_dir, planner, r["steps"], r["episodes"], r["seed"], device=job["device"], closed=kind == CLOSED
            )
            result["request"] = request
            atomic_write_bytes(path, (json.dumps(result) + "\n").encode())
            done.append(f"{kind}_{planner}")
    return {"name": run_dir.name, "done": done}


#: The planning kinds of the offline mode: open-loop plans (``--openloop``) and MPC with the frozen model
#: (``--closedloop``); a run's results are ``KIND_PLANNER.json``.
OPEN, CLOSED = "openloop", "closedloop"


def _planning_tasks(job: Mapping[str, Any]) -> list[tuple[str, str]]:
    """(kind, planner) of every planning result ``job`` asks for."""
    return [(OPEN, p) for p in job["planners"]] + [(CLOSED, p) for p in job.get("closed_planners", [])]


def offline_todo(job: Mapping[str, Any]) -> list[str]:
    """What :func:`offline_job` would do for ``job`` now: a subset of train, eval, openloop_PLANNER."""
    run_dir = Path(job["run_dir"])
    todo = [] if (run_dir / "config.yaml").is_file() else ["train"]
    if todo or not json_matches(run_dir / "eval.json", job["eval_request"]):
        todo.append("eval")
    todo += [
        f"{kind}_{p}"
        for kind, p in _planning_tasks(job)
        if todo[:1] == ["train"]
        or not json_matches(run_dir / f"{kind}_{p}.json", {**job[f"{kind}_request"], "planner": p})
    ]
    return todo


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
    backend: Backend | None = None,
    preset: str = "research",
    device: str = "auto",
    overrides: Sequence[str] = (),
    protocol: str = "pets",
    progress: bool = True,
    arms: Mapping[str, tuple[str, Mapping[str, str]]] | None = None,
    configs_only: bool = False,
    data_seeds: Sequence[int] = (0,),
) -> dict[str, Any]:
    """Collect, train, evaluate (and open-loop plan) everything missing, then write the summaries.

    ``test_episodes`` None: 20, or under a protocol with a test-set size, enough episodes of the env's length.
    ``backend``: where the runs run (default: one local worker, one thread per run).
    ``arms``: ``{label: (model, overrides)}`` for the names in ``models`` that are arms (``--arm``), not models.
    ``configs_only``: return ``{"configs": {run name: resolved config}}`` once the arguments are checked, without
    looking at ``out`` or running anything (``--print-config``).
    ``data_seeds``: the data sets (``--data-seeds``): every model and seed is trained and evaluated on each
    (:func:`data_paths`, :func:`collect_seeds`); runs pair by (data seed, seed).

    Returns ``{"data": {file: collected|reused}, "todo": {run: [what was missing]}, "done": {run: [what was
    done]}, "failed": {run: message}, "summary"}``; runs absent from "todo" were reused as they were.
    """
    import envs
    from pets.config import ConfigError, parse_overrides
    from pets.data.protocols import get_protocol
    from pets.learning.offline import offline_config

    backend = backend or Backend()

    try:
        proto = get_protocol(protocol)
    except ValueError as err:
        raise UsageError(str(err)) from None
    steps = sac_steps(policy, protocol)
    if steps is not None:
        policy = f"sac:{steps}"

    def n_test(env: str) -> int:
        if test_episodes is not None:
            return test_episodes
        if proto.test_samples is None:
            return 20
        return -(-proto.test_samples // (max_steps or envs.get(env).episode_length))

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
    expected_policy_name(policy)
    try:
        extra = parse_overrides(list(overrides))
    except ConfigError as err:
        raise UsageError(str(err)) from None
    for key in ("seed", "head", "env", "device"):
        if key in extra:
            raise UsageError(f"{key}= is set by the command itself; do not pass it as an override")
    extra["threads"] = str(backend.threads)
    out = Path(out).resolve()
    jobs, data_actions, pending, configs = [], {}, {}, {}
    data_seeds = list(dict.fromkeys(int(d) for d in data_seeds))
    if not data_seeds or min(data_seeds) < 0:
        raise UsageError(f"--data-seeds must be ints >= 0, got {data_seeds}")
    for env in env_names:
        for model in models:
            head, own = (arms or {}).get(model, (model, {}))
            for seed in seeds:
                try:
                    expected = offline_config(
                        env, head, {**extra, **own}, preset=preset, seed=seed, device=device, protocol=protocol
                    )
                except ConfigError as err:
                    raise UsageError(str(err)) from None
                for d in data_seeds:
                    configs[run_name(env, model, seed, data_seed=d)] = expected
                    run_dir = out / "runs" / run_name(env, model, seed, data_seed=d)
                    if not configs_only and (run_dir / "config.yaml").is_file():  # the searched architecture is the
                        searched = ("model.hidden_size", "model.num_layers") if proto.architectures(env) else ()
                        ignore = (*NOT_COMPARED, *searched, *left_to_auto({**extra, **own}))  # run's own choice
                        check_same_config(run_dir, expected, ignore=ignore)
    if configs_only:
        return {"configs": configs}
    check_out_writable(out)  # after every argument is checked: bad input leaves no directory behind
    data_dir = out / "data"
    eval_request = {
        "horizons": sorted(set(int(h) for h in horizons)),
        "starts": starts,
        "seed": EVAL_SEED,
        "mode": "mean",
        # standardized_error is scaled by the training data's observation std (eval.json files from before
        # this key was added standardized by the test data, without the per-part errors: they are redone)
        "standardized_by": "train data",
    }
    openloop_request = {"steps": openloop_steps, "episodes": openloop_episodes, "seed": OPENLOOP_SEED}
    closedloop_request = {"steps": closedloop_steps, "episodes": openloop_episodes, "seed": OPENLOOP_SEED}
    for env in env_names:
        for model in models:
            head, own = (arms or {}).get(model, (model, {}))
            for seed, d in ((seed, d) for d in data_seeds for seed in seeds):
                name = run_name(env, model, seed, data_seed=d)
                train_path, test_path = data_paths(data_dir, env, d)
                job = {
                    "env": env,
                    "model": head,
                    "seed": seed,
                    "data_seed": d,
                    "run_dir": str(out / "runs" / name),
                    "train_data": str(train_path),
                    "test_data": str(test_path),
                    "overrides": {**extra, **own},
                    "preset": preset,
                    "protocol": protocol,
                    "device": device,
                    "eval_request": {**eval_request, "data": f"data/{test_path.name}"},
                    "planners": list(planners) if openloop else [],
                    "openloop_request": openloop_request,
                    "closed_planners": list(planners) if closedloop else [],
                    "closedloop_request": closedloop_request,
                }
                todo = offline_todo(job)
                if todo:
                    jobs.append((name, offline_job, (job,)))
                    pending[name] = todo
    total = len(env_names) * len(models) * len(seeds) * len(data_seeds)
    alone = backend.kind == "local" and backend.workers == 1  # a job's own progress bar only when it runs here
    with open_backend(backend, out, needed=bool(jobs)) as run:  # Ray: connected and checked before any work
        data_jobs = []
        for env, d in ((env, d) for env in env_names for d in data_seeds):  # existing files checked here; missing
            missing = []  # ones collected on the backend, a job per data set
            train_path, test_path = data_paths(data_dir, env, d)
            (train_seed, test_seed), n_tests = collect_seeds(d), n_test(env)
            parts = (("train", train_path, train_seed, episodes), ("test", test_path, test_seed, n_tests))
            for part, path, seed, n in parts:
                part_policy = f"sb3:{sac_agent_path(train_path)}" if steps is not None and part == "test" else policy
                if path.is_file() or policy == EXISTING:
                    try:
                        data_actions[path.name] = prepare_data(path, env, part_policy, n, seed, max_steps)
                    except ValueError as err:  # e.g. the SAC agent file went missing
                        raise UsageError(f"{path.name}: {err}") from None
                else:
                    missing.append((str(path), part_policy, n, seed))
            if missing:
                args = (env, missing, max_steps, progress and alone, backend.threads)
                data_jobs.append((f"{env} data {d}", collect_data, args))
        data_failed = {}
        for name, (ok, value) in run(data_jobs, processes=True, progress=progress, desc="data sets").items():
            if ok:
                data_actions.update({file: "collected" for file in value})
            else:
                env, _, d = name.split()
                data_failed[env, int(d)] = value
        if data_failed:  # the runs of a data set that could not be made fail with the reason; the others go on
            jobs = [job for job in jobs if (job[2][0]["env"], job[2][0]["data_seed"]) not in data_failed]
        print(
            f"{PROG}: {total} runs: {total - len(jobs)} reused, {len(jobs)} with work to do "
            f"({backend.describe()}); data: " + ", ".join(f"{k} {v}" for k, v in data_actions.items()),
            file=sys.stderr,
        )
        warning = few_seeds_warning(len(seeds))
        if warning:
            print(warning, file=sys.stderr)
        results = run(jobs, processes=True, progress=progress, desc="offline runs")
    for (env, d), message in data_failed.items():
        for model in models:
            for seed in seeds:
                results[run_name(env, model, seed, data_seed=d)] = (False, f"no data: {message}")
    failed = {name: msg for name, (ok, msg) in results.items() if not ok}
    done = {name: res["done"] for name, (ok, res) in results.items() if ok}
    summary = summarise_offline(out, env_names, models, seeds, eval_request, failed, data_seeds=data_seeds)
    if openloop:
        summarise_openloop(out, env_names, models, seeds, planners, openloop_request)
    if closedloop:
        summarise_openloop(out, env_names, models, seeds, planners, closedloop_request, kind=CLOSED)
    return {"data": data_actions, "todo": pending, "done": done, "failed": failed, "summary": summary}
