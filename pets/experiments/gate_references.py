"""The locomotion gate's reference agents, read as runs (:class:`Reference`): SB3's SAC from its training
collection (``python -m pets.collect --policy sac:STEPS``) and mbrl-lib's PETS from the per-trial CSV of
``docs/scripts/peer_mbrl.py learn --arms mbrl-lib``. :func:`pets.experiments.gate.reference_row` makes the gate's
row of one.

A reference that ran to a smaller registered budget than the gate's (mbrl-lib: 50k env steps, the gate's amendment
of 2026-11-28 21:45 UTC) is complete at that budget; the summary then reads its endpoint there
(:func:`pets.experiments.gate.endpoint_budget`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: The agent name of each reference.
SAC, MBRL = "sac", "mbrl-lib"


@dataclass(frozen=True)
class Reference:
    """One reference run: its episodes as metrics-like rows (``env_steps`` cumulative, ``episode_reward``,
    ``episode_length``, ``terminated``), its process CPU seconds and those spent planning (NaN if unknown; SAC
    plans none) and its budget (None: the gate's)."""

    env: str
    agent: str
    seed: int
    rows: list[dict[str, Any]]
    cpu_s: float = math.nan
    plan_cpu_s: float = math.nan
    budget: int | None = None


def sac_run(path: Path) -> Reference:
    """A SAC collection (a data set holding every episode SAC trained on, in order; the last one cut at STEPS). Its
    CPU seconds: the number in ``PATH.cpu_s`` beside the data set where one was written (the collection's process
    CPU time, e.g. ``/usr/bin/time -f "%U %S"`` summed), else unknown."""
    from pets.data.datasets import load_dataset

    data = load_dataset(path)
    if not str(data["policy"] if "policy" in data else "").startswith("sac:"):
        policy = str(data["policy"]) if "policy" in data else "not recorded"
        raise ValueError(f"{path} is not a SAC collection (pets.collect --policy sac:STEPS); its policy: {policy}")
    rows, steps = [], 0
    for rew, term, n in zip(data["rew"], data["terminated"], data["lengths"]):
        steps += int(n)
        rows.append({"env_steps": steps, "episode_reward": float(np.nansum(rew[:n])), "episode_length": int(n),
                     "terminated": int(bool(term[:n].any()))})  # fmt: skip
    beside = path.with_suffix(".cpu_s")
    cpu_s = float(beside.read_text()) if beside.is_file() else math.nan
    return Reference(str(data["env"]), SAC, int(data["seed"]) if "seed" in data else -1, rows, cpu_s, 0.0)


def peer_runs(path: Path) -> list[Reference]:
    """The mbrl-lib runs of a ``peer_mbrl.py learn`` CSV (its ``mbrl-lib`` rows, one per trial; an episode shorter
    than the env's length ended by termination, a fall), each complete at the env steps its trials reached."""
    import envs
    from pets.experiments.report import read_csv_rows

    runs: dict[tuple[str, int], list[dict[str, str]]] = {}
    for r in read_csv_rows(path):
        if r["impl"] == MBRL:
            runs.setdefault((envs.get(r["env"]).name, int(r["seed"])), []).append(r)
    out = []
    for (env, seed), trials in runs.items():
        length = envs.get(env).episode_length
        rows = [{"env_steps": int(r["env_steps"]), "episode_reward": float(r["episode_reward"]),
                 "episode_length": int(r["episode_length"]), "terminated": int(int(r["episode_length"]) < length)}
                for r in trials]  # fmt: skip
        cpu_s = float(trials[-1]["run_cpu_s"])
        out.append(Reference(env, MBRL, seed, rows, cpu_s, budget=rows[-1]["env_steps"]))
    return out
