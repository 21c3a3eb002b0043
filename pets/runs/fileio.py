"""Atomic file writes and the run-directory lock: a file is replaced whole or not at all, one run per directory.

Temporary files are named ``.NAME.XXXXXXXX.tmp`` (:data:`TEMP_SUFFIX`): a failed write removes its own, and
:func:`locked` removes those a killed process (kill -9 mid-write) left in the directory it takes over.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: The lock file a running command holds in its run directory.
LOCK_FILE = ".lock"
#: The suffix of every temporary file this module writes (hidden names: ``.NAME.XXXXXXXX.tmp``).
TEMP_SUFFIX = ".tmp"
#: The file that makes a directory a run directory: the run's resolved config, written at its start.
CONFIG_FILE = "config.yaml"


def _file_mode() -> int:
    """The mode ``open()`` gives a new file: 0o666 less the process umask."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


_FILE_MODE = _file_mode()


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a uniquely named temporary file in the same directory and ``os.replace``;
    the temporary file is removed if the write fails (a full disk leaves nothing behind). An OSError names
    ``path``, where the OS named no file (ENOSPC from ``write``) or the temporary one (``os.replace`` onto a
    directory), which is gone by then."""
    path = Path(path)
    try:
        _write_replace(path, data)
    except OSError as err:
        if err.filename is None or Path(err.filename).name.endswith(TEMP_SUFFIX):
            err.filename, err.filename2 = str(path), None
        raise


def _write_replace(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TEMP_SUFFIX)
    try:
        os.fchmod(fd, _FILE_MODE)  # mkstemp makes 0600 files; results are as readable as any file written here
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def writable_dir_error(directory: Path) -> str | None:
    """Why files cannot be written in ``directory`` (created if needed), or None if they can: checked by creating
    and removing a temporary file, before any long work starts."""
    try:
        Path(directory).mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=directory, prefix=".probe.", suffix=TEMP_SUFFIX)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        return f"{directory} is not a writable directory ({err.strerror or err})"
    return None


def run_dir_error(directory: Path) -> str | None:
    """Why ``directory`` is not a run directory (no :data:`CONFIG_FILE`), or None if it is. A directory that holds
    only the lock is named as what it is: a run killed (kill -9) in its first seconds, before it wrote its config."""
    directory = Path(directory)
    if (directory / CONFIG_FILE).is_file():
        return None
    if directory.is_dir() and [p.name for p in directory.iterdir()] == [LOCK_FILE]:
        return (
            f"{directory} holds no run: the run started there was stopped in its first seconds, before it wrote "
            f"its {CONFIG_FILE} (nothing was lost); run its command again with --out {directory}"
        )
    return f"{directory} is not a run directory (no {CONFIG_FILE})"


def new_run_dir_error(directory: Path, advice: str = "pick a new or empty --out") -> str | None:
    """Why a new run cannot start in ``directory`` though it holds no run (no :data:`CONFIG_FILE`): it holds other
    files, which the run would write over or mix with its own; None where it is new, empty, or holds only the lock and
    temporary files (a run stopped in its first seconds, which its command starts again there)."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    names = (p.name for p in directory.iterdir())
    other = sorted(n for n in names if n != LOCK_FILE and not (n.startswith(".") and n.endswith(TEMP_SUFFIX)))
    if not other:
        return None
    shown = ", ".join(other[:3]) + (f" and {len(other) - 3} more" if len(other) > 3 else "")
    return f"{directory} is not empty and holds no run ({shown}): a new run would write its files among them; {advice}"


class DirectoryInUse(RuntimeError):
    """Another process (``holder``: its pid, or ``unknown``) holds the lock of a directory."""

    def __init__(self, message: str, holder: str = "unknown") -> None:
        super().__init__(message)
        self.holder = holder


@contextmanager
def locked(directory: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``directory`` (created if needed) while the block runs.

    The lock is the OS's (``flock`` on ``directory/.lock``): released on any exit, kill -9 included, so a lock left
    by a killed run is never stale. DirectoryInUse if another process holds it. Once held, the temporary files a
    killed holder left behind are removed (no one else writes there).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    fd = os.open(directory / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            raise DirectoryInUse(f"{directory} is in use by another run (process {holder})", holder) from None
        try:  # who holds it, for the message of a second run; the lock holds without it (a full disk)
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError:
            pass
        remove_temporaries(directory)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def remove_temporaries(directory: Path) -> list[Path]:
    """Remove the temporary files of this module (``.*.tmp``) in ``directory``; the removed paths. Only for a
    directory whose lock is held: another writer's file in progress would go too."""
    removed = []
    for path in Path(directory).glob(f".*{TEMP_SUFFIX}"):
        if path.is_file():
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed


def remove_if_unused(directory: Path, created: bool) -> None:
    """After a run that failed before writing anything: remove the lock file of ``directory`` if it is the only thing
    there, and the directory itself, empty (before the lock was taken) or so emptied, if this command ``created`` it
    (no folder holding only ``.lock``, or nothing, is left)."""
    directory = Path(directory)
    try:
        names = [p.name for p in directory.iterdir()]
        if names not in ([], [LOCK_FILE]):
            return
        if names:
            (directory / LOCK_FILE).unlink()
        if created:
            directory.rmdir()
    except OSError:  # gone, or another process put something there meanwhile: leave it
        pass
