"""``python -m pets.compare``: the A/B comparison command, kept under this name; the code is :mod:`pets.experiments`."""

from __future__ import annotations

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """pets.experiments.cli's main (imported here on first use)."""
    from pets.tools.cli import interrupts_deferred

    with interrupts_deferred():  # never a module half-imported
        from pets.experiments.cli import main as compare
    return compare(argv)


if __name__ == "__main__":
    from pets.tools.cli import run_command

    run_command("pets.compare", main, sigterm=True)  # SIGTERM stops the sweep as Ctrl-C does
