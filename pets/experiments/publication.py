"""What one study publishes, as one unit (:class:`Publication`): its committed per-seed rows, the files
``pets.compare report`` makes from them (:class:`Product`), the generated blocks of the docs it renders and the doc
pages that hold them. A study declares its unit in its own module as ``PUBLICATION``; the one table of units is
:data:`pets.experiments.published.PUBLICATIONS`, from which report takes everything it makes and checks.

Paths are relative to the repository root; products run with that root (or a copy of its docs/results) as the
working directory, and a block renders from such a tree (``tree / RESULTS / ...``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

RESULTS = "docs/results"
FIGURES = "docs/figures"


def results_path(name: str) -> str:
    """``docs/results/NAME``."""
    return f"{RESULTS}/{name}"


@dataclass(frozen=True)
class Product:
    """Files ``outputs`` that ``make()`` writes (relative to the working directory) from committed ``inputs``."""

    name: str
    outputs: tuple[str, ...]
    inputs: tuple[str, ...]
    make: Callable[[], None]


@dataclass(frozen=True)
class Publication:
    """One study's published part. ``raw``: its committed per-seed (or per-trial) rows, the data nothing
    regenerates; ``products``: its generated files, in the order they are made (a product's inputs before it);
    ``blocks``: its generated doc blocks, ``<!-- report:NAME -->`` name -> the block's text rendered from a tree;
    ``pages``: the doc pages of its own that hold blocks (beside README.md and docs/*.md, which any study may use);
    ``not_generated``: committed summaries of the study that report does not make, each with why."""

    name: str
    raw: tuple[str, ...] = ()
    products: tuple[Product, ...] = ()
    blocks: Mapping[str, Callable[[Path], str]] = field(default_factory=dict)
    pages: tuple[str, ...] = ()
    not_generated: Mapping[str, str] = field(default_factory=dict)
