"""Run a script with one atomic write stopped halfway, to be killed there (tests/test_faults.py).

    python -m tests.stall_write NAME N MARKER SCRIPT [ARGS ...]

Runs SCRIPT (e.g. run_pets.py) as ``__main__``. Its N-th atomic write of a file named NAME (``pets.runs.fileio``) is
stopped just before the data reach the disk for good: the temporary file is cut to half its bytes, MARKER is
created, and the process sleeps until it is killed. The code under test runs unchanged up to that point.
"""

from __future__ import annotations

import os
import runpy
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str]) -> None:
    name, nth, marker, script, *args = argv
    temporaries: dict[int, str] = {}
    writes = {"n": 0}
    real_mkstemp, real_fsync = tempfile.mkstemp, os.fsync

    def mkstemp(*a, **kw):  # noqa: ANN002, ANN003 - tempfile.mkstemp's own signature
        fd, path = real_mkstemp(*a, **kw)
        temporaries[fd] = path
        return fd, path

    def fsync(fd: int) -> None:
        path = temporaries.pop(fd, None)
        if path is not None and Path(path).name.startswith(f".{name}."):
            writes["n"] += 1
            if writes["n"] == int(nth):
                os.ftruncate(fd, os.fstat(fd).st_size // 2)
                Path(marker).touch()
                time.sleep(3600)
        real_fsync(fd)

    tempfile.mkstemp, os.fsync = mkstemp, fsync
    sys.argv = [script, *args]
    runpy.run_path(script, run_name="__main__")


if __name__ == "__main__":
    main(sys.argv[1:])
