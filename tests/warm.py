"""``run``: ``subprocess.run`` for this project's Python commands, forked from a warm process.

Each Python command the suite starts pays Python's and torch's start-up (~1.2 CPU-s here) before it does its
work; the suite starts a few hundred. ``run`` keeps them real processes (their own pid, exit status, signals, files)
but forks each from a server that has imported torch, the commands' modules and the envs, and run nothing else: no
thread besides OpenBLAS's pool (which handles fork; checked before every fork) and no torch op, so no OpenMP pool
is inherited. The child sets up what a fresh ``python script.py ...`` would have (argv, ``sys.path[0]``, cwd,
environment, standard streams, fresh entropy for Python's, numpy's and torch's global generators), runs the command
as ``__main__`` and exits as Python does (``SystemExit`` codes, an uncaught exception's traceback and exit 1, an
uncaught ``KeyboardInterrupt`` as death by SIGINT, atexit handlers, non-daemon threads).

What a forked child cannot have, ``run`` leaves to a fresh process (``subprocess.run`` with the same arguments):
another interpreter, ``python -c``/flags, keyword arguments it does not take, and environment variables read at
start-up (``PYTHON*``, OpenMP/MKL, CUDA, ``MUJOCO_GL``, ``LD_*``, the locale) that differ from a server's, a server
being kept per value of those. Two things a forked child shares with its server, so the tests whose point they are
keep ``subprocess.run``: the hash seed of ``str`` (cross-process reproducibility), and the start-up itself
(imports, entry points, a Ctrl-C during them). The warm-up must print nothing, or ``run`` refuses to use the
server: a command's first warning belongs in its own stderr. test_warm.py pins the equivalence with
``subprocess.run``."""

from __future__ import annotations

import atexit
import json
import locale
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Modules the commands import; the server imports them once.
WARM_MODULES = tuple(
    "torch torch._dynamo numpy envs mujoco pets.config pets.loop pets.compare pets.collect pets.train pets.evaluate"
    " pets.openloop".split()
)
#: Environment variables read at start-up (by Python, OpenMP, MKL, CUDA, MuJoCo's GL choice, the loader).
STARTUP_PREFIXES = tuple("PYTHON OMP_ KMP_ MKL_ GOMP_ CUDA CUBLAS TORCH MUJOCO_GL PYOPENGL LD_ MALLOC LANG LC_".split())
#: Set (to anything) in the suite's environment, every command runs in a fresh Python (``subprocess.run``); off
#: Linux too (the fork's safety is checked through /proc; macOS's system libraries do not survive a fork).
FRESH_VARIABLE = "PETS_TESTS_FRESH"
#: ``subprocess.run`` keyword arguments ``run`` takes (anything else goes to ``subprocess.run``).
ACCEPTED = {"cwd", "env", "capture_output", "text", "timeout", "check", "input", "stdout", "stderr"}


def run(cmd, **kwargs) -> subprocess.CompletedProcess:
    """``subprocess.run(cmd, **kwargs)``, forked from a warm server where the command allows it (see the module)."""
    argv = [str(a) for a in cmd]
    if os.environ.get(FRESH_VARIABLE) or sys.platform != "linux" or not _forkable(argv, kwargs):
        return subprocess.run(cmd, **kwargs)
    env = {str(k): str(v) for k, v in (os.environ if kwargs.get("env") is None else kwargs["env"]).items()}
    return _server(_startup_env(env)).run(argv, **{**kwargs, "env": env})


def _forkable(argv: list[str], kwargs: dict) -> bool:
    if set(kwargs) - ACCEPTED or len(argv) < 2 or argv[0] != sys.executable:
        return False
    if kwargs.get("stdout") not in (None, subprocess.PIPE) or kwargs.get("stderr") not in (None, subprocess.PIPE):
        return False
    cwd = kwargs.get("cwd") or os.getcwd()
    if not os.path.isdir(cwd):
        return False  # subprocess.run raises for it
    if argv[1] == "-m":
        return len(argv) > 2
    script = os.path.join(cwd, argv[1])
    return not argv[1].startswith("-") and argv[1].endswith(".py") and os.path.isfile(script)  # else Python's error


def _startup_env(env: dict) -> tuple:
    return tuple(sorted((k, v) for k, v in env.items() if k.startswith(STARTUP_PREFIXES)))


_SERVERS: dict[tuple, _Server] = {}
_LOCK = threading.Lock()


def _server(key: tuple) -> _Server:
    with _LOCK:
        server = _SERVERS.get(key)
        if server is None or server.pid != os.getpid() or server.proc.poll() is not None:
            server = _SERVERS[key] = _Server(dict(key))
        return server


class _Server:
    """One warm process (``python -c 'import tests.warm; tests.warm.serve()'``) and its request pipe."""

    def __init__(self, startup_env: dict):
        env = {k: v for k, v in os.environ.items() if not k.startswith(STARTUP_PREFIXES)} | startup_env
        self.pid = os.getpid()
        self.log = tempfile.NamedTemporaryFile(prefix="warm-server-", suffix=".log", delete=False)
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "import tests.warm; tests.warm.serve()"],
            cwd=ROOT,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.log,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        self.lock = threading.Lock()
        ready = self._read(timeout=600)
        warm_up = Path(self.log.name).read_text()
        if ready.get("ready") is not True or warm_up:
            self.proc.kill()
            raise RuntimeError(f"the warm server did not start cleanly: {ready}; it printed:\n{warm_up}")
        atexit.register(self.close)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            self.proc.wait(timeout=30)
        os.unlink(self.log.name)

    def _read(self, timeout: float | None) -> dict:
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        if not ready:
            raise TimeoutError
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the warm server died (exit {self.proc.wait()}): {Path(self.log.name).read_text()}")
        return json.loads(line)

    def run(
        self,
        argv,
        *,
        env,
        cwd=None,
        capture_output=False,
        text=False,
        timeout=None,
        check=False,
        input=None,
        stdout=None,
        stderr=None,
    ) -> subprocess.CompletedProcess:
        with self.lock, tempfile.TemporaryDirectory(prefix="warm-") as tmp:
            paths = {name: os.path.join(tmp, name) for name in ("in", "out", "err")}
            data = input.encode() if isinstance(input, str) else input
            Path(paths["in"]).write_bytes(data or b"")
            request = {
                "argv": argv,
                "cwd": str(cwd or os.getcwd()),
                "env": env,
                "stdin": paths["in"] if data else None,
                "stdout": paths["out"],
                "stderr": paths["err"],
            }
            self.proc.stdin.write((json.dumps(request) + "\n").encode())
            self.proc.stdin.flush()
            child = self._read(timeout=60)["pid"]
            try:
                status = self._read(timeout)["status"]
                expired = False
            except TimeoutError:
                os.kill(child, signal.SIGKILL)
                status, expired = self._read(timeout=60)["status"], True
            out, err = (Path(paths[name]).read_bytes() for name in ("out", "err"))
        captured = capture_output or stdout == subprocess.PIPE, capture_output or stderr == subprocess.PIPE
        if not captured[0]:
            sys.stdout.write(out.decode(errors="replace"))
        if not captured[1]:
            sys.stderr.write(err.decode(errors="replace"))
        out, err = (_decode(b, text) if keep else None for b, keep in ((out, captured[0]), (err, captured[1])))
        if expired:
            raise subprocess.TimeoutExpired(argv, timeout, out, err)
        proc = subprocess.CompletedProcess(argv, status, out, err)
        if check:
            proc.check_returncode()
        return proc


def _decode(data: bytes, text: bool):
    """As ``subprocess.run(text=True)`` does: the locale's encoding, universal newlines."""
    if not text:
        return data
    return data.decode(locale.getpreferredencoding(False)).replace("\r\n", "\n").replace("\r", "\n")


# The server side -------------------------------------------------------------------------------------------------


def serve() -> None:
    """Import the commands' modules, then fork one child per request line on stdin until it closes."""
    import importlib

    import numpy  # noqa: F401  (OpenBLAS starts its thread pool here; its fork handlers make the fork safe)

    blas_threads = _threads()
    for name in WARM_MODULES:
        importlib.import_module(name)
    channel = os.fdopen(os.dup(1), "w")
    base_path = sys.path[1:]  # sys.path[0] is the server's "" (its cwd)
    _send(channel, {"ready": _threads() <= blas_threads, "threads": _threads()})
    for line in sys.stdin.buffer:
        request = json.loads(line)
        if _threads() > blas_threads:
            return  # something started threads (an OpenMP pool?): forking is no longer safe; the client sees EOF
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            channel.close()
            _child(request, base_path)
        _send(channel, {"pid": pid})
        _, status = os.waitpid(pid, 0)
        _send(channel, {"status": os.waitstatus_to_exitcode(status)})


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def _send(channel, message: dict) -> None:
    channel.write(json.dumps(message) + "\n")
    channel.flush()


def _child(request: dict, base_path: list[str]) -> None:
    """Become ``python argv[1:]`` in ``cwd`` with ``env``; never returns."""
    import atexit as exits
    import random
    import runpy

    import numpy
    import torch

    code = 0
    try:
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        random.seed()  # fresh entropy for the global generators, as in a fresh process
        numpy.random.seed()
        torch.seed()
        for fd, path, flags in (
            (0, request["stdin"] or os.devnull, os.O_RDONLY),
            (1, request["stdout"], os.O_WRONLY | os.O_CREAT),
            (2, request["stderr"], os.O_WRONLY | os.O_CREAT),
        ):
            opened = os.open(path, flags)
            os.dup2(opened, fd)
            os.close(opened)
        argv = request["argv"][1:]
        if argv[0] == "-m":
            sys.argv, first = ["-m", *argv[2:]], os.getcwd()
        else:
            sys.argv, first = argv, os.path.dirname(os.path.realpath(argv[0]))
        sys.path[:] = [first, *base_path]
        if argv[0] == "-m":
            sys.modules.pop(argv[1], None)  # a fresh Python has not imported the module it runs
            main = sys.modules["__main__"].__dict__  # the server's: a fresh one holds only these
            kept = {"__builtins__": main["__builtins__"], "__annotations__": {}}
            main.clear()
            main.update(kept)
            runpy._run_module_as_main(argv[1])  # what ``python -m`` calls: argv[0] the module's file, as it stays
        else:
            runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as stop:
        code = _exit_code(stop.code)
    except BaseException as error:
        tb = error.__traceback__
        while tb is not None and tb.tb_frame.f_code.co_filename in (__file__, "<frozen runpy>"):
            tb = tb.tb_next  # the traceback a fresh Python prints starts at the command's own frame
        sys.excepthook(type(error), error.with_traceback(tb), tb)
        code = -signal.SIGINT if isinstance(error, KeyboardInterrupt) else 1
    try:
        threading._shutdown()  # Python's own exit waits for non-daemon threads
        exits._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        if code == -signal.SIGINT:
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGINT)
        os._exit(code & 0xFF)


def _exit_code(code) -> int:
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1
