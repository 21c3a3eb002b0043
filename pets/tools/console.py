"""The console scripts (pyproject.toml, ``[project.scripts]``): each runs its command as ``python -m`` does, through
:func:`pets.tools.cli.run_command`, so Ctrl-C at any moment, the command's own imports included, is one line and exit
130, never a traceback. The command is imported only inside it (this module imports nothing heavy)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NoReturn

from pets.tools import forward
from pets.tools.cli import import_main, run_command


def _tool(name: str) -> Callable[[], NoReturn]:
    """The console script of ``pets.tools.NAME`` (``python -m pets.NAME``)."""

    def script() -> NoReturn:
        forward("__main__", name)
        raise AssertionError("unreachable: run_command exits")

    script.__doc__ = f"``pets-{name.replace('_', '-')}``: ``python -m pets.{name}``."
    return script


def _command(prog: str, module: str, sigterm: bool = False) -> Callable[[], NoReturn]:
    """The console script of ``module.main`` (imported with Ctrl-C deferred; ``sigterm``: SIGTERM is a Ctrl-C)."""

    def script() -> NoReturn:
        run_command(prog, lambda: import_main(module)(), sigterm=sigterm)

    script.__doc__ = f"``{prog}``: ``{module}.main``."
    return script


run_pets = _command("run_pets.py", "run_pets")
# pets.compare: its main imports pets.experiments with Ctrl-C deferred; SIGTERM stops its sweep as Ctrl-C does
compare = _command("pets.compare", "pets.compare", sigterm=True)
collect = _tool("collect")
train = _tool("train")
evaluate = _tool("evaluate")
openloop = _tool("openloop")
oracle = _tool("oracle")
visualize = _tool("visualize")
onestep = _tool("onestep")
bench = _tool("bench")
