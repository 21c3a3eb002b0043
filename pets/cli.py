"""What every command-line entry point shares: one-line usage errors and their exit status."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

#: Exit status of every command on bad input (as run_pets.py).
EXIT_USAGE = 2
#: Exit status of a run that failed on good input (model training diverged, or planning got no finite return).
EXIT_FAILED = 3


class OneLineParser(argparse.ArgumentParser):
    """argparse with usage errors as one stderr line ``PROG: error: ...`` and exit code 2."""

    def error(self, message: str) -> NoReturn:
        fail(self.prog, message)


def fail(prog: str, message: str, code: int = EXIT_USAGE) -> NoReturn:
    """Print ``PROG: error: MESSAGE`` (on one line) to stderr and exit with status ``code`` (2: bad input)."""
    line = " ".join(str(message).split()) or "unknown error"
    print(f"{prog}: error: {line}", file=sys.stderr)
    raise SystemExit(code)
