"""Run directories of a comparison: their names, the compared arms, and checks of what a directory holds."""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from pets.experiments.arguments import UsageError


def check_out_writable(out: Path) -> None:
    """Create ``out`` if needed; UsageError unless files can be written in it (before any work)."""
    from pets.runs.fileio import writable_dir_error

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file, not a directory; pick another --out")
    problem = writable_dir_error(out)
    if problem:
        raise UsageError(f"--out: {problem}; pick another --out")


def check_new_run_dir(run_dir: Path) -> None:
    """UsageError where a run to start cannot be made in ``run_dir``: it or ``OUT/runs`` is a file, or it holds other
    files; refused before any run starts, not failed as the run starts."""
    from pets.runs.fileio import new_run_dir_error

    if run_dir.parent.is_file():  # OUT/runs
        raise UsageError(f"{run_dir.parent} is a file, not the folder of the run directories; move or delete it")
    if run_dir.is_file():
        raise UsageError(f"{run_dir} is a file, not the run directory of a run to start; move or delete it")
    if problem := new_run_dir_error(run_dir, "move its files away, or pick another --out"):
        raise UsageError(problem)


def env_stem(env: str) -> str:
    """An env's name in file and directory names: an import path ``module:ATTR`` by its spec's name (a colon breaks
    scp, rsync, Windows and TensorBoard; ``envs.file_name``), a catalogue name as it is."""
    if ":" not in env:
        return env
    from envs import file_name

    return file_name(env)


def run_name(env: str, model: str, seed: int, planner: str | None = None, data_seed: int = 0) -> str:
    """The run directory's name: ``ENV-MODEL-sSEED``, ``ENV-MODEL-PLANNER-sSEED`` when planners are compared, and
    ``ENV-MODEL-dDATA-sSEED`` for offline runs on data set DATA > 0 (data set 0 keeps the plain name)."""
    data = f"-d{data_seed}" if data_seed else ""
    env = env_stem(env)
    return f"{env}-{model}{data}-s{seed}" if planner is None else f"{env}-{model}-{planner}{data}-s{seed}"


def arm_run_dir(runs: Path, env: str, model: str, seed: int, planner: str | None) -> Path:
    """The run directory of an arm's seed in ``runs`` (``OUT/runs``): :func:`run_name`'s, but where planners are
    compared and that does not exist, the run of the model and seed made without ``--planners`` (ENV-MODEL-sSEED)
    when its config.yaml names this planner: the same run, reused (or refused if its config differs otherwise), not
    run again under a new name."""
    named = Path(runs) / run_name(env, model, seed, planner)
    plain = Path(runs) / run_name(env, model, seed)
    if planner is None or named.exists() or not (plain / "config.yaml").is_file():
        return named
    import yaml

    try:
        cfg = yaml.safe_load((plain / "config.yaml").read_text())
    except (OSError, ValueError, yaml.YAMLError):  # unreadable: not this arm's run (the plain arm refuses it)
        return named
    ran = cfg.get("planner") if isinstance(cfg, dict) else None
    return plain if isinstance(ran, dict) and ran.get("name") == planner else named


def budget_of(run_dir: Path) -> tuple[int | None, int]:
    """A run's env-step budget (``max_env_steps``; None: none) and its episodes' step limit, from its config.yaml
    (``(None, 0)`` without one)."""
    import yaml

    from pets.experiments.gate import full_length

    path = Path(run_dir) / "config.yaml"
    cfg = yaml.safe_load(path.read_text()) if path.is_file() else None
    if not isinstance(cfg, dict) or cfg.get("max_env_steps") is None:
        return None, 0
    return int(cfg["max_env_steps"]), full_length(cfg)


def cut_by_budget(rows: Sequence[Mapping[str, Any]], max_env_steps: int | None, episode_length: int) -> bool:
    """Whether the run's last episode was cut by its env-step budget ``max_env_steps``: the budget reached there and
    the episode not complete (:func:`pets.experiments.gate.complete`: ended neither by itself nor at its step limit
    ``episode_length``)."""
    from pets.experiments.gate import complete

    if max_env_steps is None or not rows or int(float(rows[-1]["env_steps"])) < max_env_steps:
        return False
    return not complete(rows[-1], episode_length)


def arm_label(model: str, planner: str | None) -> str:
    """What the summaries call one compared arm: the model, or ``MODEL+PLANNER`` when planners are compared."""
    return model if planner is None else f"{model}+{planner}"


def online_arms(models: Sequence[str], planners: Sequence[str] | None) -> list[tuple[str, str | None]]:
    """The compared (model, planner) pairs; the planner is None when planners are not compared."""
    return [(m, p) for m in models for p in (planners if planners is not None else [None])]


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


#: Config keys a run directory may differ in from the command: the trial count (a run can be extended) and the
#: threads (speed; float rounding at most, not the experiment).
NOT_COMPARED = ("trials", "threads")


#: Keys whose ``auto`` (their default) is resolved by the machine that makes a run's config (``pets.runs.hardware``):
#: on a cluster of mixed CPU kinds the runs of one study may hold different concrete values for them.
PRECISION_KEYS = ("planner.precision", "model.precision")


#: Resolved by the machine too where a preset leaves it at ``auto`` (``pets.config.AUTO_BOOL_KEYS``): compiled
#: training follows the resolved precision. Elsewhere its default is false, which no run of the sweep changes.
COMPILE_KEYS = ("model.compile",)


def left_to_auto(overrides: Mapping[str, Any]) -> tuple[str, ...]:
    """The :data:`PRECISION_KEYS` and :data:`COMPILE_KEYS` that ``overrides`` does not set: a run made on another
    machine may hold either concrete value for them, so a rerun does not compare them."""
    return tuple(k for k in (*PRECISION_KEYS, *COMPILE_KEYS) if str(overrides.get(k, "auto")) == "auto")


def precision_note(run_dirs: Iterable[Path]) -> list[str]:
    """Markdown lines naming the precisions and training paths (``model.compile``) the runs in ``run_dirs`` used,
    when they are not all the same (else none): set so by an arm, or ``auto`` resolved on machines of different CPU
    kinds or for runs begun with different trial counts."""
    from omegaconf import OmegaConf

    used: dict[str, list[str]] = {}
    for run_dir in run_dirs:
        path = Path(run_dir) / "config.yaml"
        if path.is_file():
            cfg = OmegaConf.load(path)
            key = " / ".join(str(OmegaConf.select(cfg, k, default="fp32")) for k in PRECISION_KEYS)
            key += ", compiled training" if OmegaConf.select(cfg, "model.compile", default=False) else ""
            used.setdefault(key, []).append(Path(run_dir).name)
    if len(used) < 2:
        return []
    return [
        "## The runs used different precisions or training paths",
        "",
        f"Not every run used the same {' / '.join(PRECISION_KEYS)} and model.compile. An arm's own overrides may set "
        "them on purpose; left at auto (the default) they resolve when a run is begun: bf16 on CPUs with native "
        "bf16 and fp32 elsewhere, so a study spread over machines of different CPU kinds mixes them; compiled "
        "training with bf16 there, for runs begun with 10 trials or more, so a study extended with --trials past "
        "10 mixes them too. Either changes the bits, not the expected outcome: bf16 moves planned returns by "
        "~6e-4 relative and holdout errors by < 0.1 % (docs/performance.md); for an A/B free of it, pass the "
        "three keys explicitly.",
        "",
        *[f"- {key}: {len(names)} runs ({', '.join(sorted(names))})" for key, names in sorted(used.items())],
        "",
    ]


def config_differences(run_dir: Path, expected: Any, ignore: Iterable[str] = NOT_COMPARED) -> list[str]:
    """``key: found != expected`` for every config key where ``run_dir/config.yaml`` differs from ``expected``."""
    from omegaconf import OmegaConf

    from pets.config import load_config

    found = _flatten(OmegaConf.to_container(load_config(str(run_dir / "config.yaml"))))
    want = _flatten(OmegaConf.to_container(expected))
    skip = set(ignore)
    return [
        f"{k}: {found.get(k)!r} != {want.get(k)!r}"
        for k in sorted(set(found) | set(want))
        if k not in skip and found.get(k) != want.get(k)
    ]


def refuse_online_run(run_dir: Path, out: Path) -> None:
    """UsageError where an offline comparison's run directory is an online run's (run_pets.py keeps its
    ``history.csv``): its model would be evaluated as if trained on the offline data, its summary replaced."""
    from pets.runs.rundir import HISTORY_FILE

    if (run_dir / HISTORY_FILE).is_file():
        raise UsageError(
            f"{run_dir} is an online run (run_pets.py), not an offline one: --out {out} holds an online comparison; "
            "pick another --out"
        )


def check_same_config(run_dir: Path, expected: Any, ignore: Iterable[str] = NOT_COMPARED) -> None:
    """UsageError if the run in ``run_dir`` was made with another config than ``expected``."""
    from omegaconf.errors import OmegaConfBaseException

    from pets.runs.rundir import written_config

    try:
        diff = config_differences(run_dir, expected, ignore)
    except (ValueError, OmegaConfBaseException) as err:
        raise UsageError(
            f"{run_dir}/config.yaml cannot be read ({str(err).splitlines()[0]}); "
            "move that run directory away or pick another --out"
        ) from None
    if diff and diff[0].startswith("imports:") and "imports" not in written_config(run_dir):
        raise UsageError(  # a run made before the key, by a script that imported the modules itself
            f"{run_dir} was made before the config key imports; add `imports: {list(expected.imports)}` to its "
            "config.yaml (docs/api.md), or pick another --out"
        )
    if diff:
        raise UsageError(
            f"{run_dir} was made with another config ({'; '.join(diff[:4])}"
            f"{'; ...' if len(diff) > 4 else ''}); pass the same settings or pick another --out"
        )


def json_matches(path: Path, request: Mapping[str, Any]) -> bool:
    """Whether ``path`` holds a result made for exactly ``request`` (its ``"request"`` entry)."""
    if not path.is_file():
        return False
    try:
        return json.loads(path.read_text()).get("request") == json.loads(json.dumps(request))
    except (ValueError, AttributeError):
        return False
