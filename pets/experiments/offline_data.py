"""The offline protocol's data sets: their files and collection seeds, collected with ``pets.collect`` or reused.

Per env a training and a separate test data set (``DIR/data/ENV-train.npz`` with data seed 0 and E episodes,
``DIR/data/ENV-test.npz`` with data seed 1 and E2 episodes, same policy), reused if present (an error if they were
collected with another policy, seed or episode count); data set D > 0 is ``ENV-dD-{train,test}.npz``, collected with
seeds 100 D and 100 D + 1. ``--policy existing`` takes both files as they are; ``--policy sac[:STEPS]`` trains SAC
and keeps every transition as the training data, saves the agent as ``ENV-sac.zip`` and rolls it for the test
episodes (:mod:`pets.experiments.offline`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from pets.experiments.arguments import UsageError

#: Data seeds of the offline mode: training data, test data, open-loop initial states.
TRAIN_DATA_SEED, TEST_DATA_SEED, OPENLOOP_SEED = 0, 1, 2
#: Data set D > 0 (``--data-seeds``) collects with seeds ``D * DATA_SEED_STRIDE + TRAIN_DATA_SEED / TEST_DATA_SEED``
#: (SAC trained with the training seed), so that no two data sets share a random stream.
DATA_SEED_STRIDE = 100
#: ``--policy`` value that uses the data files already in DIR/data as they are.
EXISTING = "existing"


def data_paths(data_dir: Path, env: str, data_seed: int = 0) -> tuple[Path, Path]:
    """The training and test files of one data set: ``ENV-{train,test}.npz`` (data set 0), else
    ``ENV-dD-{train,test}.npz``."""
    from pets.experiments.rundirs import env_stem

    stem = f"{env_stem(env)}-d{data_seed}" if data_seed else env_stem(env)
    return data_dir / f"{stem}-train.npz", data_dir / f"{stem}-test.npz"


def collect_seeds(data_seed: int = 0) -> tuple[int, int]:
    """The collection seeds (training, test) of data set ``data_seed``."""
    return data_seed * DATA_SEED_STRIDE + TRAIN_DATA_SEED, data_seed * DATA_SEED_STRIDE + TEST_DATA_SEED


def checked_data_seeds(data_seeds: Sequence[int]) -> list[int]:
    """The data seeds without repeats, in order; UsageError if none, or one is negative or makes a collection seed
    past numpy's and SB3's 32 bits (:func:`collect_seeds`: data set D collects with 100 D and 100 D + 1)."""
    from pets.limits import MAX_SEED

    data_seeds = list(dict.fromkeys(int(d) for d in data_seeds))
    if not data_seeds or min(data_seeds) < 0:
        raise UsageError(f"--data-seeds must be ints >= 0, got {data_seeds}")
    largest = (MAX_SEED - TEST_DATA_SEED) // DATA_SEED_STRIDE
    if max(data_seeds) > largest:
        raise UsageError(
            f"--data-seeds must be <= {largest:,} (data set D collects with seed {DATA_SEED_STRIDE} D + "
            f"{TEST_DATA_SEED}, at most 2**32 - 1), got {max(data_seeds):,}"
        )
    return data_seeds


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


def check_data_paths(data_dir: Path, env_names: Sequence[str], data_seeds: Sequence[int]) -> None:
    """UsageError, before any work, where a data file cannot be read or made: ``data_dir`` (``OUT/data``) or a data
    file's path is something else than a folder or a file (collecting there failed after the runs' checks)."""
    if data_dir.exists() and not data_dir.is_dir():
        raise UsageError(f"{data_dir} is a file, not the folder of the data sets; move or delete it")
    for path in (path for env in env_names for d in data_seeds for path in data_paths(data_dir, env, d)):
        if path.exists() and not path.is_file():
            raise UsageError(f"{path} is a directory, not a data set file; move or delete it")


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
        from pets.data.sb3 import agent_bytes, sac_checkpoint_path
        from pets.runs.fileio import atomic_write_bytes

        path.parent.mkdir(parents=True, exist_ok=True)
        checkpoint = sac_checkpoint_path(path)  # a stopped study goes on from it
        try:
            data, agent = collect_sac(
                spec, sac_steps(policy, "pets"), seed, max_steps, device="cpu", progress=progress, checkpoint=checkpoint
            )
        except ValueError as err:
            raise UsageError(str(err)) from None
        atomic_write_bytes(sac_agent_path(path), agent_bytes(agent))  # before the data: it needs it
        save_dataset(path, data)
        checkpoint.unlink(missing_ok=True)
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
