"""What every command-line entry point shares: one-line errors and their exit status.

Exit status of every command, run_pets.py, pets.train, pets.collect, pets.evaluate, pets.openloop and
pets.compare (docs/cli.md, "Exit codes"; :data:`EXIT_CODES` is the one table):

- 0: done;
- 1 (:data:`EXIT_DIFFERS`): ``pets.compare report --check``: a generated file or block differs from what
  ``report`` makes (as ``diff`` exits 1); (:data:`EXIT_READER_GONE`) any command, quietly, where the reader of its
  standard output went away first (``| head``), as Python's documentation exits on EPIPE;
- 2 (:data:`EXIT_USAGE`): bad input, checked before any long work: a bad option, key or value; a missing,
  corrupt or mismatched file (checkpoint, config.yaml, data set); an output location that cannot be written
  (read-only, under /proc, a file in place of a directory); a run directory in use by another run;
- 3 (:data:`EXIT_FAILED`): the work failed on good input: model training diverged, planning got no finite
  return, or a write failed while it ran (a full disk); the run keeps what it completed before; for
  pets.compare, some of its runs failed (the summary covers the others);
- 130 (:data:`EXIT_INTERRUPTED`): interrupted (Ctrl-C; for pets.compare also SIGTERM);
- 143 (:data:`EXIT_TERMINATED`, 128 + SIGTERM): stopped by SIGTERM (``kill``, a scheduler's stop), every command
  but pets.compare: one line as for Ctrl-C, then the process ends by the signal itself, so pets.compare counts the
  run as killed from outside (its Ray backend retries it).

Each error is one stderr line ``PROG: error: MESSAGE`` that says what to do.
"""

from __future__ import annotations

import argparse
import errno
import functools
import json
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

#: Exit status of every command on bad input (as run_pets.py).
EXIT_USAGE = 2
#: Exit status after Ctrl-C (128 + SIGINT), as the shells report it.
EXIT_INTERRUPTED = 130
#: Exit status after SIGTERM (128 + SIGTERM): the process ends by the signal, after its one line (not pets.compare).
EXIT_TERMINATED = 143
#: Exit status of work that failed on good input (model training diverged, planning got no finite return, or a
#: write failed while it ran, e.g. a full disk).
EXIT_FAILED = 3
#: Exit status of ``pets.compare report --check`` when a generated file differs from what ``report`` makes.
EXIT_DIFFERS = 1
#: Exit status of a command whose standard output's reader went away before it wrote (no line: nothing failed).
EXIT_READER_GONE = 1
#: Every exit status of the commands and what it means.
EXIT_CODES = {
    0: "done",
    EXIT_DIFFERS: "pets.compare report --check: a generated file is out of date; any command: its output's reader "
    "went away first (| head)",
    EXIT_USAGE: "bad input, one line before any long work",
    EXIT_FAILED: "the work failed on good input (what completed before is kept)",
    EXIT_INTERRUPTED: "interrupted (Ctrl-C; pets.compare: SIGTERM too)",
    EXIT_TERMINATED: "stopped by SIGTERM, by the signal itself (not pets.compare); what completed before is kept",
}

#: Set by the SIGTERM handler of :func:`run_command` (not pets.compare's): the command is stopping on SIGTERM.
_terminated = threading.Event()
#: A Ctrl-C (or SIGTERM as one) reached the command: see :func:`_forget_handled_interrupt`.
_interrupted = threading.Event()


def stopped() -> str:
    """How the command was stopped, for its one line: ``interrupted`` (Ctrl-C) or ``stopped by SIGTERM``."""
    return "stopped by SIGTERM" if _terminated.is_set() else "interrupted"


class OneLineParser(argparse.ArgumentParser):
    """argparse with usage errors as one stderr line ``PROG: error: ...`` and exit code 2."""

    def error(self, message: str) -> NoReturn:
        fail(self.prog, message)


def thread_count(text: str) -> int:
    """The argparse type of ``--threads``: an int >= 0 (0: torch's default)."""
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be an int >= 0 (0: torch's default), got {text!r}")
    return n


def positive_int(text: str) -> int:
    """The argparse type of a count that must be at least one (``--repeats``, ``--epochs``, ...)."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be an int >= 1, got {text!r}")
    return n


def add_threads_option(p: argparse.ArgumentParser) -> None:
    """The tools' ``--threads`` (checked by :func:`thread_count`; :func:`set_threads` applies it)."""
    p.add_argument("--threads", type=thread_count, default=0, help="torch CPU threads (default 0: torch's default)")


def set_threads(n: int) -> None:
    """torch's CPU threads to ``n`` (0: leave torch's default)."""
    if n:
        import torch

        torch.set_num_threads(n)


def import_given(overrides: list[str]) -> None:
    """Import the modules an ``imports=[...]`` item of a command's ``key=value`` overrides names, before the command
    looks up ``--model`` and planner names (your own register there; the runs get the override too); ConfigError
    (one line) for a bad value or a module that fails (:mod:`pets.imports`)."""
    from pets.config import parse_overrides
    from pets.imports import import_modules

    import_modules(parse_overrides(overrides).get("imports", []))


def fail(prog: str, message: str, code: int = EXIT_USAGE) -> NoReturn:
    """Print ``PROG: error: MESSAGE`` (on one line) to stderr and exit with status ``code`` (2: bad input)."""
    line = " ".join(str(message).split()) or "unknown error"
    print(f"{prog}: error: {line}", file=sys.stderr)
    raise SystemExit(code)


def write_failed(prog: str, err: OSError, advice: str) -> NoReturn:
    """Exit :data:`EXIT_FAILED` with one line naming the file whose write failed, why, and ``advice``: what is kept
    and what to do, written for a full disk (``free space, then ...``). Where a directory is in the way of the file
    (EISDIR) or a file is in the way of a folder on its path (ENOTDIR), the line names it, and ``free space`` in
    ``advice`` becomes what to move."""
    line = f"writing {err.filename or 'a file'} failed ({err.strerror or err})"
    if err.errno in (errno.EISDIR, errno.ENOTDIR):
        problem, fix = _in_the_way(err)
        line, advice = f"{line}: {problem}", advice.replace("free space", fix)
    fail(prog, f"{line}; {advice}", EXIT_FAILED)


def _in_the_way(err: OSError) -> tuple[str, str]:
    """What is in the way of a write that failed with EISDIR or ENOTDIR, and what to do about it."""
    if err.errno == errno.EISDIR:
        return "it is a directory, not a file", "move or delete that directory"
    path = Path(err.filename or "")
    file = next((p for p in path.parents if p.is_file()), None)  # the folder on the path that is a file
    where = f"{file} is a file, not a folder" if file else "a file is in the way of a folder on its path"
    return where, "move or delete that file"


def write_json_result(prog: str, path: Path, result: Any) -> None:
    """Write ``result`` as indented JSON to ``path`` atomically; a failed write (a full disk) exits with
    :func:`write_failed`, saying that the results were printed."""
    from pets.runs.fileio import atomic_write_bytes

    try:
        atomic_write_bytes(path, (json.dumps(result, indent=1) + "\n").encode())
    except OSError as err:  # a full disk: the temporary file is removed
        write_failed(prog, err, "the results are printed above; free space or pick another --json")


def interruptible(prog: str, kept: str) -> Callable[[Callable[..., int]], Callable[..., int]]:
    """A ``main`` that turns Ctrl-C (KeyboardInterrupt) into one stderr line ``PROG: interrupted; KEPT`` (after SIGTERM:
    ``stopped by SIGTERM``) and exit status 130, instead of a traceback. ``kept`` says what the interrupted command
    leaves behind."""

    def wrap(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def wrapped(*args: object, **kwargs: object) -> int:
            try:
                return main(*args, **kwargs)
            except KeyboardInterrupt:
                print(f"\n{prog}: {stopped()}; {kept}", file=sys.stderr)
                return EXIT_INTERRUPTED

        return wrapped

    return wrap


@contextmanager
def interrupts_deferred(raises: type[KeyboardInterrupt] = KeyboardInterrupt) -> Iterator[None]:
    """Hold a Ctrl-C (or SIGTERM) that comes inside the block until the block ends, then raise ``raises``: imports and
    setup are never cut half-way (a module left half-imported breaks the next import of it, e.g. with a
    RecursionError, and libraries that catch too much can swallow the interrupt). Outside the main thread, where
    signals cannot be handled, it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        _interrupted.set()
        raise raises


#: What a command interrupted before its own code began says it leaves: it has written nothing.
NOTHING_WRITTEN = "nothing was written (it stopped while starting)"


class InterruptedWhileStarting(KeyboardInterrupt):
    """Ctrl-C before the command's own ``main`` began (its imports): :func:`run_command` says nothing was written."""


def import_main(module: str) -> Callable[[], int | None]:
    """``module.main``, imported with Ctrl-C deferred (never a module half-imported); a Ctrl-C during the import is
    :class:`InterruptedWhileStarting`."""
    import importlib

    with interrupts_deferred(InterruptedWhileStarting):
        return importlib.import_module(module).main


#: Libraries a Ctrl-C must never cut while they import, imported by :func:`run_command` before the command runs.
#: numpy: an interrupt inside its import can be swallowed and leave it half-imported, and the next ``np.linalg``
#: recurses until RecursionError. mujoco: an interrupt inside its extensions' initialisation becomes an ImportError
#: ("initialization failed"), which gymnasium reports as "MuJoCo is not installed" with a traceback. envs before
#: mujoco: ``import envs`` sets the headless ``MUJOCO_GL``, which mujoco reads once, on import (or nothing renders).
UNCUTTABLE_IMPORTS = ("numpy", "envs", "mujoco")


def run_command(prog: str, main: Callable[[], int | None], kept: str = "", sigterm: bool = False) -> NoReturn:
    """Run a command's ``main`` as the process and exit with its status. Ctrl-C at any moment, the command's
    imports included (``main`` imports the command's module), is one stderr line ``PROG: interrupted; KEPT`` and exit
    130, never a traceback (before the command's own code began, KEPT is :data:`NOTHING_WRITTEN`); a Ctrl-C once
    ``main`` has returned (the process ending) is ignored: the process exits with the command's status, never by
    the signal (-2). SIGTERM stops the command as Ctrl-C does, its line saying ``stopped by SIGTERM``, and then ends
    the process by SIGTERM (exit status 143: pets.compare counts its run as killed from outside, Ray retries it),
    instead of the process ending at once, silently. ``sigterm``: SIGTERM is a Ctrl-C, exit 130 (pets.compare: a sweep
    stopped by ``kill`` or a scheduler stops its runs as on Ctrl-C and says so)."""
    sys.unraisablehook = _interrupt_again(sys.unraisablehook)
    stops = (signal.SIGINT, signal.SIGTERM)
    signal.signal(signal.SIGTERM, _as_ctrl_c if sigterm else _terminate)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where it is ignored (nohup)
        signal.signal(signal.SIGINT, _ctrl_c)
    try:
        with interrupts_deferred(InterruptedWhileStarting):
            for name in UNCUTTABLE_IMPORTS:
                _import_first(prog, name)
        code = main()
    except KeyboardInterrupt as stop:
        for signum in stops:
            signal.signal(signum, signal.SIG_IGN)
        said = NOTHING_WRITTEN if isinstance(stop, InterruptedWhileStarting) else kept
        print(f"\n{prog}: {stopped()}" + (f"; {said}" if said else ""), file=sys.stderr)
        code = EXIT_INTERRUPTED
    except SystemExit as done:  # fail(): its line is printed
        code = done.code
    except BrokenPipeError:
        if not stdout_gone():
            raise  # another pipe of the command's (a child's, a socket): its own failure
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # else Python's flush at exit raises again
        code = EXIT_READER_GONE  # the reader of stdout went away (`| head`): quietly, as Python does on EPIPE
    # The work is over: a Ctrl-C while the process ends (pools, threads, files closing) is ignored. A Python handler
    # would not do: the interpreter's finalisation puts SIGINT back to its default, and the process would end by the
    # signal (-2), while an ignored signal stays ignored to the end.
    for signum in stops:
        signal.signal(signum, signal.SIG_IGN)
    if code == EXIT_INTERRUPTED and _terminated.is_set():
        _end_by_sigterm()
    _forget_handled_interrupt(code)
    sys.exit(code)


def stdout_gone() -> bool:
    """Whether standard output is a pipe whose reader has gone (``| head`` read what it wanted): ``poll`` reports
    an error on the writing end of a pipe with no reader left."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no poll (Windows), stdout closed or not a file
        return False


def _import_first(prog: str, name: str) -> None:
    """Import one of :data:`UNCUTTABLE_IMPORTS`; mujoco failing with a ``MUJOCO_GL`` set (an invalid value, a backend
    whose library is missing: ``import mujoco`` loads it) is one line and exit 2, never a traceback."""
    import importlib

    try:
        importlib.import_module(name)
    except Exception as err:
        if name != "mujoco" or not os.environ.get("MUJOCO_GL"):
            raise
        from envs.render import gl_failure

        fail(prog, gl_failure(err, "cannot be imported"))


def _terminate(signum: int, frame: Any) -> None:
    """The SIGTERM handler of a command (not pets.compare's): the command stops as on Ctrl-C (:func:`_as_ctrl_c`), its
    line says SIGTERM, and :func:`run_command` then ends the process by SIGTERM."""
    _terminated.set()
    _as_ctrl_c(signum, frame)


def _end_by_sigterm() -> NoReturn:
    """End the process by SIGTERM once the command has stopped and said so (exit status 143; ``-15`` to
    :mod:`subprocess`), as it would have ended without the handler: pets.compare counts the run as killed from outside
    (its Ray backend retries it). The exit handlers run first; the interpreter's finalisation is skipped, as the
    signal's."""
    import atexit

    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGTERM])
    signal.raise_signal(signal.SIGTERM)
    os._exit(EXIT_TERMINATED)  # not reached: the signal ends the process


def _ctrl_c(signum: int, frame: Any) -> None:
    """The SIGINT handler of a command: Python's own (KeyboardInterrupt), noting that a Ctrl-C came."""
    _interrupted.set()
    raise KeyboardInterrupt


def _as_ctrl_c(signum: int, frame: Any) -> None:
    """A SIGTERM handler: what Ctrl-C does at that moment (SIGINT's handler: deferred while importing), and a
    KeyboardInterrupt where SIGINT is ignored (a command started in the background by a shell, or with nohup, where
    SIGTERM is the one way to stop it). Once the command is over, SIGTERM is ignored as SIGINT is."""
    _interrupted.set()
    handler = signal.getsignal(signal.SIGINT)
    if not callable(handler):
        raise KeyboardInterrupt
    handler(signal.SIGINT, frame)


def _interrupt_again(hook: Callable[[Any], object]) -> Callable[[Any], object]:
    """``sys.unraisablehook`` that delivers again a Ctrl-C that landed in a finaliser or a weakref callback (an
    import's module-lock callback, a ``__del__``): Python cannot raise there, so it would print "Exception ignored"
    with a traceback and go on as if no Ctrl-C had come. Any other unraisable exception goes to ``hook``."""
    import _thread
    import time

    main = threading.main_thread().ident

    def interrupt_soon() -> None:  # once the main thread is out of the hook, where it would be ignored again
        time.sleep(0.01)
        again = signal.SIGTERM if _terminated.is_set() else signal.SIGINT  # SIGINT may be ignored (nohup)
        signal.pthread_kill(main, again)  # a real signal: it ends a sleep or a wait; ignored once ending

    def hook_or_interrupt(unraisable: Any) -> object:
        if issubclass(unraisable.exc_type, KeyboardInterrupt):
            _thread.start_new_thread(interrupt_soon, ())  # not threading's: its start() waits, in the hook
            return None
        return hook(unraisable)

    return hook_or_interrupt


def _forget_handled_interrupt(code: int | str | None) -> None:
    """CPython marks the process as ended by an unhandled Ctrl-C whenever a KeyboardInterrupt passes through code
    run by ``exec`` of a string (dataclasses, namedtuples and torch's imports run many), even when the command then
    catches it, and ends the process by SIGINT (-2) instead of its exit status. The command returned a status, so it
    handled any: clear the mark (a C global up to Python 3.11; from 3.12 it sits in the runtime state, out of reach:
    a command that a Ctrl-C reached then exits at once with its status, after the exit handlers, instead)."""
    import ctypes

    try:
        ctypes.c_int.in_dll(ctypes.pythonapi, "_Py_UnhandledKeyboardInterrupt").value = 0
    except ValueError:  # not a symbol of this Python
        if code != EXIT_INTERRUPTED and not _interrupted.is_set():
            return
        import atexit

        if code is not None and not isinstance(code, int):  # as sys.exit(text): the text, then status 1
            print(code, file=sys.stderr)
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code if isinstance(code, int) else 0 if code is None else 1)
