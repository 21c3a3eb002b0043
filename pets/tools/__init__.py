"""The command-line tools: argument parsing, checks of the input, exit statuses and printing around the library
(``pets.data``, ``pets.learning``, ``pets.planning``, ...); no library module imports them
(``tests/test_architecture.py``).

- ``collect``, ``train``, ``evaluate``, ``openloop``: data sets, offline training, long-horizon prediction error,
  open-loop planning (the library parts: :mod:`pets.data.collect`, :mod:`pets.learning.offline`,
  :mod:`pets.learning.evaluation`, :mod:`pets.planning.openloop`);
- ``onestep``: does training work? one-step error of a trained model vs the untrained network and "no change";
- ``oracle``: MPC with the true simulator as the model (a planner's failure or the model's?);
- ``visualize``: the paper's trajectory figure, rendered by MuJoCo;
- ``bench``, ``bench_train``, ``bench_layers``: planning-step, model-training and bf16-layer benchmarks;
- ``cli``: what every command shares: one-line errors and the one table of exit statuses.
- ``console``: the console scripts (``run-pets``, ``pets-compare``, ``pets-train``, ...), each run as ``python -m``
  runs it.

Each also answers at its old path, ``python -m pets.X`` and ``import pets.X`` (:func:`forward`).
"""

from __future__ import annotations

import importlib
import sys

#: The tools here, each also at ``pets.<name>`` (a forwarding module).
MOVED = (
    *("collect", "train", "evaluate", "openloop", "onestep", "oracle", "visualize"),
    *("bench", "bench_train", "bench_layers"),
)


def forward(name: str, tool: str) -> None:
    """Make the module ``name`` (an old path, ``pets.<tool>``) the tool ``pets.tools.<tool>``: run its ``main`` when
    ``name`` is ``__main__`` (``python -m pets.<tool>``), else alias it in ``sys.modules`` (so ``import pets.<tool>``
    and patches of its attributes reach the tool itself)."""
    if name == "__main__":  # a command: Ctrl-C while it imports is one line and exit 130 too
        from pets.tools.cli import import_main, run_command

        run_command(f"pets.{tool}", lambda: import_main(f"{__name__}.{tool}")())
    sys.modules[name] = importlib.import_module(f"{__name__}.{tool}")
