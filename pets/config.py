"""All configuration in one place: global defaults, per-env defaults, presets (their tables: :mod:`pets.presets`),
`key=value` overrides.

Resolution order (later wins): ``Config`` defaults -> ``ENV_DEFAULTS[env]`` -> ``PRESETS[preset]``
-> ``PRESET_ENV_DEFAULTS[(preset, env)]`` -> ``head_defaults(head)`` -> command-line ``key=value`` overrides.
Values are parsed against the declared field types (``trials=00143`` is 143, never the YAML-octal 99), then
range-checked.
"""

from __future__ import annotations

import difflib
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, make_dataclass
from functools import cache
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

from dynamics.networks import ACTIVATIONS
from gem_head.head import COMPOSE_MODES, LOSSES
from pets.errors import ConfigError
from pets.imports import import_modules
from pets.limits import schedule_problem, size_problem
from pets.models import MODELS, check_model
from pets.planning.feedback import FeedbackConfig
from pets.planning.particles import CANDIDATE_TABLE, unknown_candidates
from pets.planning.planners import PLANNER_CLASSES, ICEMConfig, MPPIConfig, check_planner_config, unknown_planner
from pets.planning.propagation import CANDIDATES, PROPAGATIONS
from pets.planning.value import ValueConfig
from pets.presets import ENV_DEFAULTS, PRESET_ENV_DEFAULTS, PRESETS, head_defaults
from pets.runs.config_files import (
    config_yaml,
    flatten,
    override_text,
    overrides_with_file,
    read_config_file,
    shared_config,
)
from pets.runs.hardware import CONCRETE_PRECISIONS

__all__ = [  # defined by their owners: the planners' and the value's configs, the config files' functions
    "ConfigError",
    "FeedbackConfig",
    "ICEMConfig",
    "MPPIConfig",
    "ValueConfig",
    "config_yaml",
    "flatten",
    "override_text",
    "overrides_with_file",
    "read_config_file",
    "shared_config",
]

#: ``--model`` values (config key ``head``): the names of ``pets.models.MODELS`` (a live view: ``register_model``).
HEADS = MODELS.keys()
#: ``planner.name`` values: the names of ``pets.planning.planners.PLANNER_CLASSES`` (a live view: ``register_planner``).
PLANNERS = PLANNER_CLASSES.keys()
AUTO_BOOL_KEYS = ("model.compile",)  # their ``auto`` is null until resolve_auto makes it true or false
PRECISIONS = ("auto", *CONCRETE_PRECISIONS)  # auto: resolved by make_config / load_config (pets.runs.hardware)
DEVICES = ("auto", "cpu", "cuda")
# The other choice lists are their owners': PROPAGATIONS and CANDIDATES (pets.planning.propagation), ACTIVATIONS
# (dynamics.networks), COMPOSE_MODES and LOSSES (gem_head.head), PLANNERS (the planner table), PRESETS (pets.presets).


@dataclass
class ModelConfig:
    ensemble_size: int = 7
    num_elites: int = 5
    hidden_size: int = 200
    num_layers: int = 4
    # silu | relu: the hidden layers' activation (dynamics.networks.ACTIVATIONS); silu (swish) is PETS' and the
    # GEM paper's, relu skips its exp (docs/performance.md, "The activation")
    activation: str = "silu"
    learn_logvar_bounds: bool = True
    lr: float = 1e-3
    batch_size: int = 256
    max_epochs: int = 50
    patience: int = 5
    holdout_ratio: float = 0.1
    max_holdout: int = 5000
    iterations: int = 0  # 0: epochs with holdout early stopping (PETS); N > 0: exactly N steps (the GEM paper)
    bootstrap: bool = True  # per-member bootstrap resamples (PETS); false: all members on the same batches
    # auto | fp32 | bf16: the training forward/backward under bfloat16 autocast (fp32 weights, loss, optimiser
    # and holdout error); auto: bf16 where the hardware has native bf16 matmuls (pets.runs.hardware), else fp32
    precision: str = "auto"
    # true: each training minibatch as one torch.compile graph (pets.learning.compiled); false: eager, the reference
    compile: bool | None = False  # auto (null; the fast preset's): where measured faster (docs/performance.md)
    # N > 0: record the holdout error every N gradient steps (TrainResult.curve; offline runs write
    # learning_curve.csv): a learning curve to check convergence; 0: none
    curve_every: int = 0


@dataclass
class PlannerConfig:
    """``planner.*``: the settings every planner shares (each planner's own section is added by :func:`schema`)."""

    name: str = "cem"
    # open_loop: candidates are action sequences (PETS); feedback: gains of a linear state-feedback law, each
    # rolled out for `horizon` steps in closed loop, replanned every step (pets.planning.feedback, docs/planning.md)
    candidates: str = "open_loop"
    population: int = 400
    elites: float = 0.1  # a ratio of the population when < 1, else a count
    iterations: int = 5
    alpha: float = 0.1  # CEM smoothing of mean and variance
    horizon: int = 30
    particles: int = 20
    propagation: str = "tsinf"
    replan_every: int = 1
    termination_penalty: float = 0.0  # subtracted from a candidate's return where it terminates (a fall) in the horizon
    # k >= 0: a candidate's return is its particles' mean return minus k x their standard deviation (pessimism
    # against the model's spread, docs/planning.md); 0: the mean, as in PETS
    risk_aversion: float = 0.0
    # The settings of one planner or candidate kind only, planner.<name>.* (feedback's: planner.feedback.*), are
    # added by schema() from their tables (PLANNER_CLASSES, CANDIDATE_TABLE: each class's `section`)
    # Speed of the rollouts (docs/performance.md)
    # auto | fp32 | bf16: the ensemble's matmuls under bfloat16 autocast (state, sampling and returns fp32); auto:
    # bf16 where the hardware has native bf16 matmuls (pets.runs.hardware), else fp32, the precise path.
    # config.yaml records the resolved value.
    precision: str = "auto"
    compile: bool = False  # torch.compile the rollout step (eager fallback with a warning if it fails)


@dataclass
class GemConfig:
    compose: str = "right"  # right: G' = G exp(alpha) (body frame); left: G' = exp(alpha) G (the paper's notation)
    loss: str = "nll"  # nll | frobenius | nll+frobenius
    frobenius_weight: float = 1.0


@dataclass
class Config:
    imports: list[str] = field(default_factory=list)  # modules imported first: your own planners, models, codecs
    env: str = "halfcheetah"
    head: str = "delta"
    trials: int = 100
    seed: int = 0
    device: str = "auto"
    threads: int = 0  # torch CPU threads; 0: torch's default. Use 1 per process when running runs in parallel
    seed_steps: int = 1000  # uniformly random steps (over as many episodes as needed) before trial 0
    episode_length: int | None = None  # None: the env's own episode length
    # A run to a threshold: stop after the first trial whose episode reward reaches it (`trials` stays the most);
    # None: always `trials` trials. pets.compare online --until-threshold sets it per env.
    stop_reward: float | None = None
    train_every: int = 0  # 0: train after every trial; N > 0: also every N env steps
    train_after_trial: bool = True  # false (with train_every=N): train only every N env steps, across episodes
    max_env_steps: int | None = None  # the run's env-step budget, seed data included; the last episode is cut at it
    video_every: int = 0  # N > 0: an MP4 of the real episode of every N-th trial (RUN/videos/trial-NNNN.mp4); 0: none
    tensorboard: bool = True  # TensorBoard event files in the run directory (when the tensorboard package is there)
    model: ModelConfig = field(default_factory=ModelConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    gem: GemConfig = field(default_factory=GemConfig)
    value: ValueConfig = field(default_factory=ValueConfig)


@cache
def _schema_class(sections: tuple[tuple[str, type], ...]) -> type:
    """:class:`Config` whose ``planner`` has the fields ``sections`` (name, dataclass) besides the shared ones."""
    names = [name for name, _ in sections]
    clash = [name for name in names if name in {item.name for item in fields(PlannerConfig)} or names.count(name) > 1]
    if clash:
        raise ConfigError(f"planner.{clash[0]} is the section of a planner or kind and another setting or section")
    own = [(name, section, field(default_factory=section)) for name, section in sections]
    planner = make_dataclass("PlannerConfig", own, bases=(PlannerConfig,))
    return make_dataclass("Config", [("planner", planner, field(default_factory=planner))], bases=(Config,))


def _sections() -> tuple[tuple[str, type], ...]:
    owners = (*PLANNER_CLASSES.items(), *CANDIDATE_TABLE.items())
    return tuple((name, cls.section) for name, cls in owners if cls.section is not None)


def schema() -> DictConfig:
    """The typed config at its defaults: :class:`Config` with the section ``planner.<name>.*`` of every planner and
    every candidate kind in their tables that has one (``pets.planning.planners``, ``pets.planning.particles``: the
    class's ``section``)."""
    return OmegaConf.structured(_schema_class(_sections()))


@cache
def _schema_keys(sections: tuple[tuple[str, type], ...]) -> tuple[str, ...]:
    return tuple(all_keys(OmegaConf.structured(_schema_class(sections))))


_POSITIVE_INTS = (
    "trials model.ensemble_size model.num_elites model.hidden_size model.num_layers model.batch_size model.max_epochs "
    "model.patience model.max_holdout planner.population planner.iterations planner.horizon planner.particles "
    "planner.replan_every value.hidden_size value.steps"
).split()
_CHOICES = {
    "planner.candidates": CANDIDATES,
    "planner.propagation": PROPAGATIONS,
    "planner.precision": PRECISIONS,
    "model.precision": PRECISIONS,
    "model.activation": tuple(ACTIVATIONS),
    "gem.compose": COMPOSE_MODES,
    "gem.loss": LOSSES,
    "device": DEVICES,
}


def all_keys(cfg: DictConfig | None = None) -> list[str]:
    """Every dotted key of ``cfg`` (e.g. ``planner.population``); of the schema if None (once per planner table)."""
    return list(_schema_keys(_sections())) if cfg is None else list(flatten(OmegaConf.to_container(cfg)))


def parse_overrides(items: list[str]) -> dict[str, str]:
    """Split ``key=value`` strings; ConfigError for a malformed item or a key given twice with different values
    (neither silently wins). Values are compared as the key's type parses them (``5`` and ``05``, ``1e3`` and
    ``1000.0`` of a float are one value; the first text is kept); a key the schema does not know (yet: a planner
    section of ``imports``) or a value it refuses compares as text."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key:
            raise ConfigError(f"expected key=value, got {item!r}")
        if out.get(key, value) != value and _parsed(key, out[key]) != _parsed(key, value):
            raise ConfigError(f"{key} is given twice ({key}={out[key]} and {key}={value}); give it once")
        out.setdefault(key, value)
    return out


def _parsed(key: str, text: str) -> Any:
    """``text`` as ``key=text`` sets it in the schema, or ``text`` itself where the schema refuses it."""
    cfg, key = schema(), DEPRECATED_KEYS.get(key, key)
    try:
        set_value(cfg, key, text)
    except ConfigError:
        return text
    return OmegaConf.select(cfg, key)


#: Flat planner keys of gem-pets 0.1 -> their nested names (still accepted, with a warning).
DEPRECATED_KEYS = {
    "planner.noise_beta": "planner.icem.noise_beta",
    "planner.icem_population_decay": "planner.icem.population_decay",
    "planner.icem_keep_elites": "planner.icem.keep_elites",
    "planner.mppi_sigma": "planner.mppi.sigma",
    "planner.mppi_temperature": "planner.mppi.temperature",
    "planner.mppi_smoothing": "planner.mppi.smoothing",
}


def _renamed(key: str) -> str:
    """``key``, or its nested name with a FutureWarning if it is a deprecated flat key."""
    if key in DEPRECATED_KEYS:
        warnings.warn(f"config key {key} is now {DEPRECATED_KEYS[key]}; the old name will go", FutureWarning, 3)
        return DEPRECATED_KEYS[key]
    return key


def set_value(cfg: DictConfig, key: str, value: Any) -> None:
    """Set ``key`` of ``cfg`` to ``value`` as an override would (lists and null from their text, types checked);
    ConfigError for an unknown key or a bad value."""
    key = _renamed(key)
    keys = all_keys()
    if key not in keys:
        close = difflib.get_close_matches(key, keys, n=1, cutoff=0.6)
        hint = f"did you mean {close[0]}? " if close else ""
        raise ConfigError(f"unknown config key {key!r}; {hint}accepted keys: {', '.join(keys)}")
    current = OmegaConf.select(cfg, key)
    if isinstance(value, str) and value.lower() in ("null", "none") and (current is None or OmegaConf.is_list(current)):
        value = None
    elif key in AUTO_BOOL_KEYS and str(value).lower() not in ("true", "false"):  # auto: null until resolve_auto
        if value not in ("auto", None):
            raise ConfigError(f"bad value for {key}: {value!r}; accepted: true, false, auto")
        value = None
    elif isinstance(value, str) and value.startswith("["):  # a list on the command line, e.g. [0, 1, 5]
        try:
            value = yaml.safe_load(value)
        except yaml.YAMLError as err:
            raise ConfigError(f"bad value for {key}: {value!r} is not a list ({str(err).splitlines()[0]})") from None
    try:
        OmegaConf.update(cfg, key, value, merge=True)
    except Exception as err:  # omegaconf's validation errors carry a multi-line message
        raise ConfigError(f"bad value for {key}: {str(err).splitlines()[0]}") from None


def _merge_nested(cfg: DictConfig, values: Mapping[str, Any]) -> None:
    for key, value in flatten(values).items():
        set_value(cfg, key, value)


def validate(cfg: DictConfig) -> None:
    """Range and choice checks that the types alone do not express."""
    if problem := size_problem(cfg, _POSITIVE_INTS):  # >= 1, and at most pets.limits.SIZE_BOUNDS
        raise ConfigError(problem)
    for key, choices in _CHOICES.items():
        if OmegaConf.select(cfg, key) not in choices:
            raise ConfigError(f"{key} must be one of {', '.join(choices)}, got {OmegaConf.select(cfg, key)!r}")
    nonnegative = ("model.lr", "planner.elites", "planner.alpha", "model.holdout_ratio", "gem.frobenius_weight")
    for key in (*nonnegative, "planner.termination_penalty", "planner.risk_aversion"):
        v = OmegaConf.select(cfg, key)
        if not math.isfinite(v) or v < 0:
            raise ConfigError(f"{key} must be a finite number >= 0, got {v}")
    if not 0 <= cfg.planner.alpha < 1:
        raise ConfigError(f"planner.alpha must be in [0, 1), got {cfg.planner.alpha}")
    if not 0 <= cfg.model.holdout_ratio < 1:
        raise ConfigError(f"model.holdout_ratio must be in [0, 1), got {cfg.model.holdout_ratio}")
    if cfg.model.num_elites > cfg.model.ensemble_size:
        raise ConfigError(
            f"model.num_elites ({cfg.model.num_elites}) must be <= model.ensemble_size ({cfg.model.ensemble_size})"
        )
    if cfg.model.iterations < 0:
        raise ConfigError(f"model.iterations must be >= 0 (0: epochs with early stopping), got {cfg.model.iterations}")
    if cfg.model.curve_every < 0:
        raise ConfigError(f"model.curve_every must be >= 0 (0: no learning curve), got {cfg.model.curve_every}")
    if cfg.threads < 0:
        raise ConfigError(f"threads must be >= 0 (0: torch default), got {cfg.threads}")
    if cfg.video_every < 0:
        raise ConfigError(f"video_every must be >= 0 (0: no videos; N: every N-th trial), got {cfg.video_every}")
    try:  # the checks of the model table and the planner table, each in its owner
        check_model(cfg.head, cfg.env, cfg.gem.compose)
        check_planner_config(cfg.planner)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if cfg.planner.replan_every > cfg.planner.horizon:
        raise ConfigError(
            f"planner.replan_every ({cfg.planner.replan_every}) must be <= planner.horizon ({cfg.planner.horizon})"
        )
    try:
        CANDIDATE_TABLE[cfg.planner.candidates].check_config(cfg.planner)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if not 0 < cfg.value.discount < 1:
        raise ConfigError(f"value.discount must be in (0, 1), got {cfg.value.discount}")
    if problem := schedule_problem(cfg):  # the run's length and when it trains
        raise ConfigError(problem)


def make_config(
    env: str, head: str = "delta", preset: str = "research", overrides: dict[str, Any] | None = None
) -> DictConfig:
    """Resolve the full config for ``env`` (a canonical env name), ``imports`` imported first, and validate it."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; accepted: {', '.join(PRESETS)}")
    overrides = {**(overrides or {}), "imports": import_modules((overrides or {}).get("imports", []))}
    cfg = schema()  # after the imports: a planner they register adds its section planner.<name>.*
    cfg.env = env
    for defaults in (ENV_DEFAULTS.get(env, {}), PRESETS[preset], PRESET_ENV_DEFAULTS.get((preset, env), {})):
        _merge_nested(cfg, defaults)
    set_value(cfg, "head", head)
    head = overrides.get("head", head)  # head=... given as an override picks its defaults too
    _merge_nested(cfg, head_defaults(head) if isinstance(head, str) else {})
    for key, value in overrides.items():
        set_value(cfg, key, value)
    validate(cfg)
    return resolve_auto(cfg)


def resolve_auto(cfg: DictConfig) -> DictConfig:
    """Replace the ``auto`` settings by the concrete ones for ``cfg.device`` on this machine (in place; returns it)."""
    from pets.runs.hardware import resolve_model_compile, resolve_precision

    for key in ("planner.precision", "model.precision"):
        OmegaConf.update(cfg, key, resolve_precision(OmegaConf.select(cfg, key), cfg.device))
    cfg.model.compile = resolve_model_compile(cfg.model.compile, cfg.model.precision, cfg.device, cfg.trials)
    return cfg


def load_run_config(run_dir: str | Path) -> DictConfig:
    """:func:`load_config` of a run directory's ``config.yaml``; ConfigError for a path that is not a run directory."""
    from pets.runs.fileio import CONFIG_FILE, run_dir_error

    if problem := run_dir_error(Path(run_dir)):
        raise ConfigError(problem)
    return load_config(Path(run_dir) / CONFIG_FILE)


def load_config(path: str | Path) -> DictConfig:
    """Load a run's resolved ``config.yaml`` into the typed schema, its ``imports`` imported first; ConfigError (one
    line, with what to do) for a file that is not YAML, is empty or truncated (no ``env``, ``head``, ``model`` or
    ``planner``), is off the schema, or whose imports fail (:mod:`pets.imports`)."""
    restore = "restore the config.yaml the run was started with (from a copy), or start a new run"
    try:
        stored = OmegaConf.load(path)
    except Exception as err:  # yaml's scanner and parser errors, a directory, an unreadable file
        raise ConfigError(f"{path} is not a readable YAML file ({str(err).splitlines()[0]}); {restore}") from None
    if not isinstance(stored, DictConfig) or len(stored) == 0:
        raise ConfigError(f"{path} is empty or not a YAML mapping; {restore}")
    missing = [key for key in ("env", "head", "model", "planner") if key not in stored]
    if missing:
        raise ConfigError(f"{path} has no {', '.join(missing)} (truncated?); {restore}")
    import_modules(stored.get("imports", []), where=str(path))  # before its planner, model and codecs are checked
    planner = stored.planner if isinstance(stored.planner, DictConfig) else {}
    if problem := unknown_candidates(planner) or unknown_planner(planner, schema().planner):
        raise ConfigError(f"{path}: {problem}")  # its kind, its planner's name, or a section of a planner of one's own
    try:
        for old, new in DEPRECATED_KEYS.items():  # a config.yaml of gem-pets 0.1 has the flat planner keys
            if OmegaConf.select(stored, old) is not None:
                OmegaConf.update(stored, new, OmegaConf.select(stored, old), merge=True)
                del stored.planner[old.split(".")[1]]
        if OmegaConf.select(stored, "model") is not None and "precision" not in stored.model:
            stored.model.precision = "fp32"  # a run from before model.precision existed trained in fp32
        cfg = OmegaConf.merge(schema(), stored)
    except Exception as err:  # a file from another version of the schema, or not a config at all
        raise ConfigError(
            f"{path} does not match this version's config schema: {str(err).splitlines()[0]}; {restore}"
        ) from None
    validate(cfg)
    return resolve_auto(cfg)
