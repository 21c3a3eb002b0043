"""The comparison arguments: program name, UsageError and the parsers of the comma-separated lists."""

from __future__ import annotations

import re
from collections.abc import Collection

from pets.experiments.statistics import MIN_SEEDS

#: The program name in every message of the comparison.
PROG = "pets.compare"


class UsageError(ValueError):
    """A bad argument or an inconsistent output directory: exit 2 with this one-line message."""


def split_list(text: str, what: str, distinct: bool = True) -> list[str]:
    """``"a,b"`` -> ``["a", "b"]`` (order kept); UsageError if empty, with empty items or (``distinct``) with an
    item twice."""
    items = [t.strip() for t in str(text).split(",")]
    if not text or not all(items):
        raise UsageError(f"--{what} must be a comma-separated list without empty items, got {text!r}")
    return unique(items, what, text) if distinct else items


def unique(items: list, what: str, text: str) -> list:
    """``items`` if no two are equal, else UsageError naming the first given twice (a study of fewer runs than the
    list reads, silently, is the mistake it prevents)."""
    seen = set()
    for item in items:
        if item in seen:
            raise UsageError(f"--{what} names {item!r} twice in {text!r}; give each once")
        seen.add(item)
    return items


#: A comma between items, not one inside a list value ``[a,b]``.
_ITEM_COMMA = re.compile(r",(?![^\[]*\])")


def split_key_values(text: str) -> list[str]:
    """``"k=v,k2=[a,b]"`` -> ``["k=v", "k2=[a,b]"]``: the items of a ``key=value`` list (``--arm``,
    ``--planner-overrides``), commas inside ``[...]`` kept with their value, empty items dropped."""
    return [item for item in _ITEM_COMMA.split(str(text)) if item]


def parse_envs(text: str) -> list[str]:
    """Canonical env names of a comma-separated list (catalogue names or gymnasium ids)."""
    import envs

    out = []
    for name in split_list(text, "envs", distinct=False):  # told apart by their canonical names below
        try:
            out.append(envs.canonical_name(name))
        except ValueError as err:
            raise UsageError(str(err)) from None
    unique(out, "envs", text)  # two spellings of one env (a name and its gymnasium id)
    _check_stems(out)
    return out


def _check_stems(names: list[str]) -> None:
    """UsageError where two envs would share file and directory names (two import paths whose specs have one name,
    or a spec named as a catalogue env): their runs would take each other's directories."""
    from envs import file_name

    seen: dict[str, str] = {}
    for name in names:
        stem = file_name(name)
        if stem in seen:
            raise UsageError(
                f"--envs {seen[stem]} and {name} both go by the name {stem!r} in run directories and files; give "
                "your specs names of their own"
            )
        seen[stem] = name


def _parse_choices(text: str, what: str, accepted: Collection[str]) -> list[str]:
    """Comma-separated names for ``--what``, each one of ``accepted``."""
    names = split_list(text, what)
    bad = [n for n in names if n not in accepted]
    if bad:
        raise UsageError(f"unknown {what[:-1]} {bad[0]!r} in --{what}; accepted: {', '.join(accepted)}")
    return names


def parse_models(text: str) -> list[str]:
    """Model (head) names, each one of ``pets.config.HEADS`` (read now, so new heads are accepted)."""
    from pets import config

    return _parse_choices(text, "models", config.HEADS)


def parse_seeds(text: str, flag: str = "--seeds") -> list[int]:
    """Seeds (of ``flag``): comma-separated ints >= 0."""
    items = split_list(text, flag.lstrip("-"), distinct=False)  # told apart as ints below
    try:
        seeds = [int(s) for s in items]
    except ValueError:
        raise UsageError(f"{flag} must be comma-separated ints >= 0 such as 0,1,2, got {text!r}") from None
    if min(seeds) < 0:
        raise UsageError(f"{flag} must be ints >= 0, got {text!r}")
    return unique(seeds, flag.lstrip("-"), text)  # 1 and 01 are one seed


def few_seeds_warning(n_seeds: int) -> str | None:
    """The one-line warning for fewer than :data:`MIN_SEEDS` seeds (None from there on). The modes print it
    to stderr once the arguments and run directories have been checked (a usage error stays one line)."""
    if n_seeds >= MIN_SEEDS:
        return None
    return (
        f"{PROG}: warning: {n_seeds} seed{'s' if n_seeds > 1 else ''}: fewer than {MIN_SEEDS} seeds cannot carry "
        "a claim (with n <= 3 the 95 % CI is the min-max of the seeds)"
    )


def parse_planners(text: str) -> list[str]:
    """Planner names, each one of ``pets.config.PLANNERS``."""
    from pets import config

    return _parse_choices(text, "planners", config.PLANNERS)


#: An arm's label: a run-directory-safe name.
_LABEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]*")
#: Keys a comparison sets itself, never an arm.
_OWN_KEYS = ("seed", "head", "env", "trials", "device", "threads")


def parse_arm(text: str) -> tuple[str, str, dict[str, str]]:
    """``LABEL=MODEL[:key=value,key=value]`` -> (label, model, overrides): a model with its own config overrides,
    compared as one more arm under its label (e.g. ``delta-det-x1=delta-det:model.ensemble_size=1,model.num_elites=1``
    beside ``delta-det``). UsageError for a bad label, model or key."""
    from pets import config

    label, sep, rest = str(text).partition("=")
    head, _, keys = rest.partition(":")
    form = "--arm must be LABEL=MODEL[:key=value,key=value]"
    if not sep or not head:
        raise UsageError(f"{form}, got {text!r}")
    if not _LABEL.fullmatch(label) or label in config.HEADS:
        raise UsageError(
            f"--arm label {label!r} must be letters, digits and _.+- and not a model name ({', '.join(config.HEADS)})"
        )
    if head not in config.HEADS:
        raise UsageError(f"unknown model {head!r} in --arm {label}; accepted: {', '.join(config.HEADS)}")
    items = split_key_values(keys)
    if any("=" not in k for k in items):
        raise UsageError(f"{form}, got {text!r}")
    overrides = dict(k.split("=", 1) for k in items)
    own = [k for k in overrides if k in _OWN_KEYS]
    if own:
        raise UsageError(f"--arm {label} sets {own[0]}=, which the comparison sets itself")
    try:
        config.parse_overrides(items)
    except config.ConfigError as err:
        raise UsageError(f"--arm {label}: {err}") from None
    return label, head, overrides


def parse_planner_overrides(text: str) -> dict[str, str]:
    """``planner.KEY=VALUE,...`` (``--planner-overrides``; a list value as ``[a,b]``) -> ``{key: value}``;
    UsageError for another form or a key outside ``planner.*`` (values are checked against a run config by the
    comparison)."""
    items = split_key_values(text)
    if any("=" not in k or not k.startswith("planner.") for k in items):
        raise UsageError(f"--planner-overrides must be planner.KEY=VALUE[,planner.KEY=VALUE...], got {text!r}")
    return dict(k.split("=", 1) for k in items)
