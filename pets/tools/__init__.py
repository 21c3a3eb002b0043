"""The command-line tools that only diagnose, benchmark or draw: no library module imports them
(``tests/test_architecture.py``).

- ``onestep``: does training work? one-step error of a trained model vs the untrained network and "no change";
- ``oracle``: MPC with the true simulator as the model (a planner's failure or the model's?);
- ``visualize``: the paper's trajectory figure, rendered by MuJoCo;
- ``bench``, ``bench_train``, ``bench_layers``: planning-step, model-training and bf16-layer benchmarks.

Each also answers at its old path, ``python -m pets.X`` and ``import pets.X`` (:func:`forward`).
"""

from __future__ import annotations

import importlib
import sys

#: The tools here, each also at ``pets.<name>`` (a forwarding module).
MOVED = ("onestep", "oracle", "visualize", "bench", "bench_train", "bench_layers")


def forward(name: str, tool: str) -> None:
    """Make the module ``name`` (an old path, ``pets.<tool>``) the tool ``pets.tools.<tool>``: run its ``main`` when
    ``name`` is ``__main__`` (``python -m pets.<tool>``), else alias it in ``sys.modules`` (so ``import pets.<tool>``
    and patches of its attributes reach the tool itself)."""
    module = importlib.import_module(f"{__name__}.{tool}")
    if name == "__main__":
        sys.exit(module.main())
    sys.modules[name] = module
