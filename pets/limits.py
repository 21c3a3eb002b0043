"""Limits before memory: every size key bounded, and the memory a config needs estimated before anything is
allocated, so that a config this machine cannot hold is refused in one line instead of being killed by the kernel
(on a shared machine an out-of-memory kill can take someone else's job).

:func:`size_problem` is part of the config's validation; :func:`memory_problem` needs the env's sizes and the
device, and runs where a command or the API is about to build a run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

#: The largest accepted value of each size key: far above any real setting (the PETS papers' largest is a
#: population of 2,500), far below what overflows or allocates before the memory estimate can speak.
SIZE_BOUNDS: dict[str, int] = {
    "trials": 1_000_000,
    "seed_steps": 1_000_000_000,
    "episode_length": 10_000_000,
    "train_every": 1_000_000_000,
    "video_every": 1_000_000,
    "threads": 4096,
    "model.ensemble_size": 1_000,
    "model.num_elites": 1_000,
    "model.hidden_size": 1_000_000,
    "model.num_layers": 1_000,
    "model.batch_size": 100_000_000,
    "model.max_epochs": 10_000_000,
    "model.patience": 10_000_000,
    "model.max_holdout": 1_000_000_000,
    "model.iterations": 1_000_000_000,
    "model.curve_every": 1_000_000_000,
    "planner.population": 10_000_000,
    "planner.iterations": 100_000,
    "planner.horizon": 100_000,
    "planner.particles": 100_000,
    "planner.replan_every": 100_000,
    "value.hidden_size": 1_000_000,
    "value.steps": 1_000_000_000,
}
#: The largest seed: numpy's global generator (seeded with it) takes 32 bits.
MAX_SEED = 2**32 - 1
BYTES = 4  # float32
GB = 1024**3


def size_problem(cfg: Any, positive: list[str]) -> str | None:
    """What is wrong with a size key of ``cfg`` (one line: the key, its value, what is accepted), or None: the keys
    ``positive`` must be >= 1, every key of :data:`SIZE_BOUNDS` at most its bound."""
    for key in positive:
        value = OmegaConf.select(cfg, key)
        if value < 1:
            return f"{key} must be >= 1, got {value}"
    for key, most in SIZE_BOUNDS.items():
        value = OmegaConf.select(cfg, key)
        if isinstance(value, int) and value > most:
            return f"{key} must be <= {most:,}, got {value:,}"
    return None


def schedule_problem(cfg: Any) -> str | None:
    """What is wrong with the run's length and training schedule (one line), or None: seeds, seed steps and
    ``train_every`` >= 0, an episode length >= 1, a finite ``stop_reward``, ``train_after_trial=false`` only with
    ``train_every=N``, and a budget ``max_env_steps`` (at most its bound) above the seed steps."""
    if cfg.seed < 0 or cfg.seed_steps < 0 or cfg.train_every < 0:
        return "seed, seed_steps and train_every must be >= 0"
    if cfg.seed > MAX_SEED:  # numpy's global seed takes 32 bits
        return f"seed must be <= {MAX_SEED:,} (2**32 - 1), got {cfg.seed:,}"
    if cfg.episode_length is not None and cfg.episode_length < 1:
        return f"episode_length must be >= 1 or null, got {cfg.episode_length}"
    if cfg.stop_reward is not None and not math.isfinite(cfg.stop_reward):
        return f"stop_reward must be a finite number or null, got {cfg.stop_reward}"
    if not cfg.train_after_trial and cfg.train_every < 1:
        return "train_after_trial=false needs train_every=N > 0 (train every N env steps), got 0"
    budget, most = cfg.max_env_steps, SIZE_BOUNDS["seed_steps"]
    if budget is not None and not cfg.seed_steps < budget <= most:
        return f"max_env_steps must be null or above seed_steps ({cfg.seed_steps:,}) and <= {most:,}, got {budget:,}"
    return None


@dataclass(frozen=True)
class Need:
    """The estimated peak bytes of one part of a run, and where it lives (``host`` memory or the ``device``)."""

    part: str
    bytes: float
    host: bool

    def __str__(self) -> str:
        return f"{self.part} ~{self.bytes / GB:,.1f} GB"


def memory_needs(cfg: Any, obs_dim: int, act_dim: int, length: int, steps: int | None = None) -> list[Need]:
    """Estimated peak memory of a run of ``cfg`` on an env of these sizes, by part (upper estimates: the network's
    input is taken as 2 obs_dim + act_dim, every float as float32). ``steps``: the env steps the replay buffer will
    hold (default: ``seed_steps`` + ``trials`` x the episode length, ``length`` where the config has none, at most
    the budget ``max_env_steps``); 0 for
    planning with a trained model only."""
    m, p = cfg.model, cfg.planner
    length = cfg.episode_length or length
    rows = cfg.seed_steps + cfg.trials * length if steps is None else steps
    if steps is None and cfg.get("max_env_steps") is not None:  # a budget of env steps ends the run first
        rows = min(rows, cfg.max_env_steps)
    width = 2 * obs_dim + act_dim
    h = m.hidden_size
    params = m.ensemble_size * (width * h + (m.num_layers - 1) * h**2 + 4 * h * obs_dim)
    candidates = p.population * p.particles
    transitions = rows * (2 * obs_dim + act_dim) * BYTES
    return [
        # the numpy buffer (host memory on every device)
        Need("replay buffer", transitions, host=True),
        # its tensors on the model's device + the normalised training inputs and targets (on a GPU, GPU memory)
        Need("training data", 2.0 * transitions, host=False),
        # weights, gradients and Adam's two moments
        Need("model weights", 4.0 * params * BYTES, host=False),
        # a minibatch's activations through every layer of every member, kept for the backward pass
        Need("training", 3.0 * m.batch_size * m.ensemble_size * m.hidden_size * m.num_layers * BYTES, host=False),
        # a rollout step: population x particles rows through the widest layers, plus the candidate sequences
        Need(
            "planning",
            (4.0 * candidates * (m.hidden_size + width) + 4.0 * p.population * p.horizon * act_dim) * BYTES,
            host=False,
        ),
    ]


def available_bytes(device: str) -> float | None:
    """Memory that can still be allocated: the free memory of the GPU ``device`` names (``cuda:N``; ``cuda``: the
    current one) for a CUDA device, else the host's (MemAvailable, or a cgroup's limit where lower); None where it
    cannot be read."""
    if device.startswith("cuda"):
        import torch

        index = torch.device(device).index
        return float(torch.cuda.mem_get_info(torch.cuda.current_device() if index is None else index)[0])
    try:
        meminfo = Path("/proc/meminfo").read_text()
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in meminfo.splitlines() if ":" in line)
    if "MemAvailable" not in fields:
        return None
    free = float(fields["MemAvailable"].split()[0]) * 1024
    limit = _cgroup_room()
    return min(free, limit) if limit is not None else free


def _cgroup_room() -> float | None:
    """What this process's cgroup (v2) may still allocate, where it has a limit."""
    base = Path("/sys/fs/cgroup")
    try:
        limit, used = (base / "memory.max").read_text().strip(), (base / "memory.current").read_text().strip()
    except OSError:
        return None
    return None if limit == "max" else float(int(limit) - int(used))


def memory_problem(
    cfg: Any,
    obs_dim: int,
    act_dim: int,
    length: int,
    device: str,
    steps: int | None = None,
    beside: tuple[int, float] = (0, 0.0),
) -> str | None:
    """One line refusing a config whose estimated memory (:func:`memory_needs`) exceeds what this machine can still
    allocate, naming the memory (host, or the GPU ``device``), the largest part and its keys; None when it fits or the
    free memory cannot be read. On a CUDA device the parts on the GPU are checked against its free memory, the rest
    against the host's. ``beside``: (how many other runs, their bytes of host memory) that run at the same time."""
    needs = memory_needs(cfg, obs_dim, act_dim, length, steps)
    on_device = device.startswith("cuda")
    host = [n for n in needs if n.host or not on_device]
    for where, parts in (("host", host), ("GPU", [n for n in needs if n not in host])):
        if not parts:
            continue
        room = available_bytes(device if where == "GPU" else "cpu")
        own = sum(n.bytes for n in parts)
        others, more = beside if where == "host" else (0, 0.0)
        if room is None or own + more <= room:
            continue
        biggest = max(parts, key=lambda n: n.bytes)
        at_once = f", {(own + more) / GB:,.1f} GB with the {others} other run(s) at once (--workers)" if others else ""
        holder = "this machine" if where == "host" else f"the GPU ({device})"
        return (
            f"this config needs about {own / GB:,.1f} GB of {where} memory ({', '.join(map(str, parts))}){at_once}, "
            f"more than the {room / GB:,.1f} GB {holder} has free; "
            f"lower {KEYS[biggest.part]}" + (" or --workers" if others else "")
        )
    return None


#: The keys that size each part of :func:`memory_needs`.
KEYS = {
    "replay buffer": "seed_steps, trials or episode_length",
    "training data": "seed_steps, trials or episode_length",
    "model weights": "model.hidden_size, model.num_layers or model.ensemble_size",
    "training": "model.batch_size, model.hidden_size or model.ensemble_size",
    "planning": "planner.population, planner.particles, planner.horizon or model.hidden_size",
}
