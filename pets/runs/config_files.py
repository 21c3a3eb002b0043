"""Config files and config text: a ``--config`` file read as dotted keys, nested settings flattened, a command's
overrides merged with its file, ``key=value`` and YAML written back, the settings a set of configs shares. Used by
:mod:`pets.config` (which re-exports these names) and the commands; nothing here knows the schema."""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

from pets.errors import ConfigError
from pets.runs.user_yaml import load_user_yaml


def read_config_file(path: str | Path) -> dict[str, Any]:
    """A config file's settings as dotted keys (``{"planner.horizon": 10}``), nested or dotted; ConfigError (one
    line) for a file not read (:mod:`pets.runs.user_yaml`) or not a mapping; keys and values checked where applied."""
    path = Path(path)
    try:
        data = load_user_yaml(path)  # bounded, no aliases
    except (OSError, ValueError) as err:  # ValueError: too big, not YAML, binary (UnicodeDecodeError), an alias
        raise ConfigError(f"--config {path}: not a readable YAML file ({str(err).splitlines()[0]})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"--config {path}: expected a mapping of config keys, got a {type(data).__name__}")
    return flatten(data)


def flatten(nested: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"planner": {"horizon": 10}}`` -> ``{"planner.horizon": 10}`` (lists are values)."""
    out: dict[str, Any] = {}
    for k, v in nested.items():
        out.update(flatten(v, f"{prefix}{k}.") if isinstance(v, Mapping) else {f"{prefix}{k}": v})
    return out


def overrides_with_file(
    path: str | Path | None, overrides: Mapping[str, Any], aside: Collection[str] = ("env", "head")
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A command's overrides with ``--config FILE``: the file's keys, then ``overrides`` (the command line wins).
    The file's keys in ``aside``, the ones the command sets through its own options (``env``, ``head``), come back
    apart, for the command to use where its option is not given. ConfigError (one line) for a bad file."""
    from_file = read_config_file(path) if path is not None else {}
    kept = {k: from_file.pop(k) for k in aside if k in from_file}
    return {**from_file, **overrides}, kept


def override_text(key: str, value: Any) -> str:
    """``key=value`` as the command line writes it (``null``, ``true``, ``[1, 2]``), e.g. a config file's setting."""
    if value is None or isinstance(value, bool | list):
        value = yaml.safe_dump(value, default_flow_style=True).splitlines()[0]
    return f"{key}={value}"


def shared_config(configs: Iterable[DictConfig], drop: Collection[str] = ()) -> tuple[dict[str, Any], list[str]]:
    """The settings every one of ``configs`` has alike, as dotted keys (less ``drop``), and the keys that differ."""
    flat = [flatten(OmegaConf.to_container(c)) for c in configs]
    same = {k: v for k, v in flat[0].items() if k not in drop and all(f.get(k, v) == v for f in flat)}
    return same, [k for k in flat[0] if k not in drop and k not in same]


def config_yaml(cfg: DictConfig | Mapping[str, Any]) -> str:
    """YAML of a resolved config or of dotted keys (nested as the schema), valid as a ``--config`` file."""
    if not isinstance(cfg, DictConfig):
        nested: dict[str, Any] = {}
        for key, value in cfg.items():
            *parents, last = key.split(".")
            node = nested
            for part in parents:
                node = node.setdefault(part, {})
            node[last] = value
        cfg = OmegaConf.create(nested)
    return OmegaConf.to_yaml(cfg)
