"""The config key ``imports``: modules imported before a config is checked, where your own planners
(``register_planner``), models (``register_model``), group codecs (``register_codec``) and error metrics of
``pets.evaluate`` (``register_metric``) register themselves.

``imports=[my_planner]`` on the command line (or ``imports=my_planner``, one name), ``imports: [my_planner]`` in a
``--config`` file, ``imports=["my_planner"]`` in the Python API. A run's ``config.yaml`` records the list, so
``--resume``, ``pets.PETS.load``, ``pets.load_model``, ``pets.evaluate`` and ``pets.openloop`` import the modules
again (:func:`pets.config.load_config`). A module imports from the folder the command runs in, as ``--env
module:ATTR`` does (:func:`envs.custom.user_folder_importable`).
"""

from __future__ import annotations

import importlib
from typing import Any

import yaml
from omegaconf import ListConfig, OmegaConf

from envs.custom import user_folder_importable
from pets.errors import ConfigError

__all__ = ["import_modules", "module_names"]

_EXAMPLE = "imports=[my_planner] or imports=[my_planner,my_model]"


def _line(err: BaseException) -> str:
    """The first line of an error's message."""
    text = str(err).strip()
    return text.splitlines()[0] if text else "no message"


def _is_module_name(name: str) -> bool:
    """``name`` is a module name as ``import`` takes it: dotted identifiers, no relative dots."""
    return bool(name) and all(part.isidentifier() for part in name.split("."))


def module_names(value: Any) -> list[str]:
    """The module names of an ``imports`` value: a list of names (a tuple or an omegaconf list too), its
    command-line text ``[a, b]``, or one name as a string; ConfigError (one line) for anything else (a number, a
    mapping, an empty or non-string item, a file name or path instead of a module name)."""
    if value is None or isinstance(value, str) and value.strip().lower() in ("", "null", "none", "~"):
        value = []  # imports=, imports=null: none, as imports=[]
    if isinstance(value, str):
        text = value.strip()
        try:
            value = yaml.safe_load(text) if text.startswith("[") else [text]
        except yaml.YAMLError as err:
            raise ConfigError(f"imports: {text!r} is not a list ({_line(err)}); e.g. {_EXAMPLE}") from None
    if isinstance(value, ListConfig):
        value = OmegaConf.to_container(value)
    if not isinstance(value, list | tuple):
        raise ConfigError(f"imports must be a list of module names ({_EXAMPLE}; imports=[] for none), got {value!r}")
    for name in value:
        if not isinstance(name, str) or not name.strip():
            raise ConfigError(f"imports must be a list of non-empty module names ({_EXAMPLE}), got {list(value)!r}")
        if name.endswith(".py") or "/" in name or "\\" in name:
            module = name.replace("\\", "/").rsplit("/", 1)[-1].removesuffix(".py")
            raise ConfigError(
                f"imports: {name!r} is a file name; give the module name ({module}), and run the command from the "
                "folder that holds the file (or put that folder on PYTHONPATH)"
            )
        if not _is_module_name(name.strip()):
            raise ConfigError(
                f"imports: {name!r} is not a module name (dotted Python identifiers, as `import` takes them); "
                f"a list is written {_EXAMPLE}"
            )
    return [name.strip() for name in value]


def import_modules(names: Any, where: str = "") -> list[str]:
    """Import each module of ``names`` (an ``imports`` value, checked by :func:`module_names`) from the current
    folder or ``sys.path``, in order; returns the names. ConfigError (one line, prefixed by ``where``, e.g. the
    config.yaml it was read from) for a bad value, a module that is not found, or one that raises (or exits) while
    it is imported."""
    try:
        checked = module_names(names)
        user_folder_importable()
        for name in checked:
            _import(name)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}" if where else str(err)) from None
    return checked


def _import(name: str) -> None:
    """Import module ``name``; ConfigError (one line, with what to do) where it cannot be."""
    try:
        importlib.import_module(name)
    except ModuleNotFoundError as err:
        if err.name is not None and (name == err.name or name.startswith(f"{err.name}.")):
            raise ConfigError(
                f"imports: cannot import {name!r} ({_line(err)}); run the command from the folder that holds "
                f"{name.split('.')[0]}.py (or put that folder on PYTHONPATH), or drop it from imports"
            ) from None
        raise ConfigError(
            f"imports: importing {name!r} failed (ModuleNotFoundError: {_line(err)}); install what it imports"
        ) from None
    except SystemExit as err:  # a script given as a module: its main ran, not only its registrations
        raise ConfigError(
            f"imports: importing {name!r} exited (SystemExit: {err.code}); a module in imports should only register "
            "(put a script's main under `if __name__ == '__main__':`)"
        ) from None
    except Exception as err:  # the module raised: a SyntaxError, a failed register_planner, ...
        raise ConfigError(
            f"imports: importing {name!r} failed ({type(err).__name__}: {_line(err)}); fix the module, or drop it "
            "from imports"
        ) from None


def definition(obj: Any) -> str:
    """Where ``obj`` (a class or a function; an instance: its class) is defined, ``module.qualname``: a module of
    ``imports`` imported again registers the same definition again, as new objects, which a table accepts."""
    owner = obj if hasattr(obj, "__qualname__") else type(obj)
    return f"{getattr(owner, '__module__', '')}.{getattr(owner, '__qualname__', '')}"
