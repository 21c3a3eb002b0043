"""Offline training protocols (``--protocol`` of ``pets.train`` and ``pets.compare offline``).

- ``pets``: PETS-style training of the config's model: per-member bootstrap resamples, a random holdout from the
  training data, early stopping on it (``pets.learning.trainer``); every transition of the data file is used.
- ``paper``: the GEM paper's (Appendix "Hyperparameters", "Ensemble Details"): 100k training and 10k validation
  samples (a random split of the data file's transitions, the same for every model and seed), Adam with lr 5e-4,
  batch 10, 10,000 iterations, no early stopping; the hidden layers searched over [100], [100, 100],
  [100, 100, 100] ([512] x 1..3 for Ant and Humanoid) and picked on the validation error; ensembles of 5 members
  averaged and trained in unison (the same batches, the summed loss). The paper's single models are
  ``model.ensemble_size=1 model.num_elites=1``. The test set (20k samples) is the evaluation data.

docs/experiments.md describes both; the config keys they set are those of ``pets.config``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Seed of the train/validation split: one split per data file, shared by every model and seed.
SPLIT_SEED = 0


@dataclass(frozen=True)
class Protocol:
    """One offline protocol: config keys it sets, sample counts, and the architectures it searches."""

    name: str
    config: dict[str, Any] = field(default_factory=dict)
    train_samples: int | None = None  # None: all transitions (less a holdout the trainer splits off itself)
    val_samples: int | None = None  # None: no separate validation set
    test_samples: int | None = None  # the evaluation data's size (pets.compare collects it)
    search: dict[str, tuple[tuple[int, int], ...]] = field(default_factory=dict)  # env -> (hidden, layers) options

    def architectures(self, env: str) -> tuple[tuple[int, int], ...]:
        """The ``(model.hidden_size, model.num_layers)`` candidates for ``env`` (empty: no search)."""
        return self.search.get(env, self.search.get("*", ()))


_SMALL = ((100, 1), (100, 2), (100, 3))
_LARGE = ((512, 1), (512, 2), (512, 3))

PROTOCOLS: dict[str, Protocol] = {
    "pets": Protocol("pets"),
    "paper": Protocol(
        "paper",
        config={
            "model.lr": 5e-4,
            "model.batch_size": 10,
            "model.iterations": 10_000,
            "model.bootstrap": False,
            "model.ensemble_size": 5,
            "model.num_elites": 5,
        },
        train_samples=100_000,
        val_samples=10_000,
        test_samples=20_000,
        search={"*": _SMALL, "ant": _LARGE, "humanoid": _LARGE},
    ),
}


def get_protocol(name: str) -> Protocol:
    """The protocol called ``name``; ValueError naming the accepted ones otherwise."""
    if name not in PROTOCOLS:
        raise ValueError(f"unknown protocol {name!r}; accepted: {', '.join(PROTOCOLS)}")
    return PROTOCOLS[name]


def split_samples(n: int, protocol: Protocol, seed: int = SPLIT_SEED) -> tuple[np.ndarray, np.ndarray]:
    """(train, validation) transition indices of a data set with ``n`` transitions under ``protocol``.

    Without a validation set: all indices for training, none for validation. Otherwise a random split (``seed``)
    with the protocol's sizes; a smaller file keeps their ratio (validation = n * val / (train + val), at least
    1), a larger one leaves the rest unused.
    """
    if protocol.val_samples is None:
        return np.arange(n), np.zeros(0, np.int64)
    train, val = protocol.train_samples or n, protocol.val_samples
    if n < 2:
        raise ValueError(f"the {protocol.name} protocol needs at least 2 transitions, got {n}")
    if n < train + val:
        val = max(1, round(n * val / (train + val)))
        train = n - val
    perm = np.random.default_rng(seed).permutation(n)
    return np.sort(perm[:train]), np.sort(perm[train : train + val])
