"""``python -m pets.compare``: the A/B comparison command, kept under this name; the code is :mod:`pets.experiments`."""

from __future__ import annotations

import sys

from pets.experiments.cli import main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
