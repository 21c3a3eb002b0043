"""The offline protocol's run jobs: train, evaluate and plan one (env, model, seed) where it lacks that result.

Per run: train offline (``pets.learning.offline.train_offline``) unless the run directory holds a trained model;
evaluate on the test data (``pets.evaluate``) into ``eval.json`` unless it holds this evaluation already; open-loop
plan per planner into ``openloop_PLANNER.json`` and MPC with the frozen model into ``closedloop_PLANNER.json`` where
asked (:mod:`pets.experiments.offline`). A job killed part way is redone whole (``config.yaml`` is written last).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.arguments import UsageError
from pets.experiments.rundirs import check_new_run_dir, check_same_config, json_matches, refuse_online_run
from pets.runs.fileio import atomic_write_bytes


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
    from pets.learning.offline import killed_training_files, train_offline
    from pets.planning.openloop import open_loop
    from pets.runs.fileio import locked

    run_dir, done = Path(job["run_dir"]), []
    if not (run_dir / "config.yaml").is_file():
        if killed_training_files(run_dir):  # a job killed (kill -9) as it wrote the run: redone whole
            with locked(run_dir):
                for path in killed_training_files(run_dir):
                    path.unlink()
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
        result["request"], result["machines"] = request, _machines(eval_path, "train" in done)
        atomic_write_bytes(eval_path, (json.dumps(result) + "\n").encode())
        if load_config(str(run_dir / "config.yaml")).tensorboard:  # per-horizon errors, TensorBoard (pets.runs.tblog)
            write_events(run_dir, job["test_data"], result)
        done.append("eval")
    for kind, planner in _planning_tasks(job):
        path = run_dir / f"{kind}_{planner}.json"
        request = {**job[f"{kind}_request"], "planner": planner}
        if "train" in done or not json_matches(path, request):
            r = request
            result = open_loop(
                run_dir,
                planner,
                r["steps"],
                r["episodes"],
                r["seed"],
                overrides=r.get("overrides"),
                device=job["device"],
                closed=kind == CLOSED,
            )
            result["request"] = request
            atomic_write_bytes(path, (json.dumps(result) + "\n").encode())
            done.append(f"{kind}_{planner}")
    return {"name": run_dir.name, "done": done}


def _machines(eval_path: Path, trained: bool) -> dict[str, str | None]:
    """Where the run was trained and evaluated (:func:`pets.experiments.report.machine_label`) for its eval.json:
    this machine, the training's kept from the eval.json before where the run was not trained here (None if
    unknown)."""
    import socket

    from pets.experiments.report import machine_label
    from pets.runs.hardware import cpu_name

    here = machine_label(socket.gethostname(), cpu_name())
    before = None
    if not trained and eval_path.is_file():
        try:
            before = (json.loads(eval_path.read_text()).get("machines") or {}).get("train")
        except (ValueError, AttributeError):  # a damaged or older eval.json: the training's machine is unknown
            before = None
    return {"train": here if trained else before, "eval": here}


#: The planning kinds of the offline mode: open-loop plans (``--openloop``) and MPC with the frozen model
#: (``--closedloop``); a run's results are ``KIND_PLANNER.json``.
OPEN, CLOSED = "openloop", "closedloop"


def _planning_tasks(job: Mapping[str, Any]) -> list[tuple[str, str]]:
    """(kind, planner) of every planning result ``job`` asks for."""
    return [(OPEN, p) for p in job["planners"]] + [(CLOSED, p) for p in job.get("closed_planners", [])]


def check_run_dir(run_dir: Path, out: Path, expected: Any, ignore: Sequence[str]) -> None:
    """UsageError, before any run, for a run directory its job cannot use: one holding an online run, a trained run
    without its checkpoint or a run made with another config than ``expected`` (``ignore``: the keys not compared),
    or, for a run to train, one that is a file (or ``OUT/runs`` is) or holds other files than those of a job killed
    as it wrote the run (redone whole)."""
    from pets.learning.offline import killed_training_files

    if (run_dir / "config.yaml").is_file():
        refuse_online_run(run_dir, out)
        if not (run_dir / "checkpoint.pt").is_file():  # its evaluation failed "no trial completed" at every rerun
            raise UsageError(
                f"{run_dir} holds a trained run's config.yaml but no checkpoint.pt: its model is gone; delete the "
                "run directory to train it again"
            )
        check_same_config(run_dir, expected, ignore=ignore)
    elif not killed_training_files(run_dir):
        check_new_run_dir(run_dir)


def offline_todo(job: Mapping[str, Any]) -> list[str]:
    """What :func:`offline_job` would do for ``job`` now: a subset of train, eval, openloop_PLANNER; UsageError where
    that is to evaluate or plan with a trained model whose checkpoint.pt is damaged (:func:`check_checkpoint`)."""
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
    if todo and todo[0] != "train":
        check_checkpoint(run_dir)
    return todo


def check_checkpoint(run_dir: Path) -> None:
    """UsageError, before any work, where a trained run's checkpoint.pt is not a whole torch file: not a zip
    archive, cut off, or with bytes that fail their CRC (the file read once, not unpickled as torch.load would)."""
    import zipfile

    from pets.runs.rundir import CHECKPOINT_FILE

    path = run_dir / CHECKPOINT_FILE
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
            pickled = any(name.endswith("/data.pkl") for name in archive.namelist())
        why = f"{bad} fails its CRC" if bad else None if pickled else "no data.pkl in it"
    except (OSError, zipfile.BadZipFile, EOFError, ValueError) as err:  # cut off, not a zip, a damaged entry
        why = str(err).splitlines()[0] if str(err) else type(err).__name__
    if why:
        raise UsageError(
            f"{path} is damaged ({why}): its model cannot be evaluated or planned with; restore it from a copy, or "
            "delete the run directory to train it again"
        )
