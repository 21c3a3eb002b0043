"""tests/warm.py's ``run`` against ``subprocess.run``: the same exit status, stdout and stderr byte for byte, for the
commands' refusals and help, a short run's metrics, and how a Python process ends (exit codes, an uncaught exception,
Ctrl-C, threads, atexit, stdin, cwd, environment, argv and ``sys.path``)."""

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests import warm
from tests.processes import alive
from tests.tiny import TINY_MODEL, TINY_PLANNER

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """\
import atexit, os, sys, threading, time
print("argv", sys.argv[1:], "path0", sys.path[0], "cwd", os.getcwd(), "FOO", os.environ.get("FOO"))
print(sys.argv[0], __name__, __spec__)
atexit.register(lambda: print("atexit ran"))
threading.Thread(target=lambda: (time.sleep(0.2), print("thread ended"))).start()
how = sys.argv[1]
if how == "stdin":
    print("read", sys.stdin.read())
if how == "text":
    sys.exit("a message")
if how == "code":
    print("to stderr", file=sys.stderr)
    sys.exit(3)
if how == "raise":
    raise ValueError("boom")
if how == "interrupt":
    raise KeyboardInterrupt
"""


@pytest.fixture(scope="module")
def script(tmp_path_factory):
    path = tmp_path_factory.mktemp("warm") / "main.py"
    path.write_text(SCRIPT)
    return path


def both(cmd, **kwargs):
    """``cmd`` through ``warm.run`` and ``subprocess.run``, with the same arguments."""
    return warm.run(cmd, **kwargs), subprocess.run(cmd, **kwargs)


def assert_same(warm_proc, fresh):
    assert (warm_proc.returncode, warm_proc.stdout, warm_proc.stderr) == (fresh.returncode, fresh.stdout, fresh.stderr)


@pytest.mark.parametrize("how", ["ok", "stdin", "text", "code", "raise", "interrupt"])
def test_a_script_ends_as_a_fresh_python_ends_it(script, tmp_path, how):
    kwargs = dict(cwd=tmp_path, env={"FOO": "bar", "PATH": "/usr/bin:/bin"}, capture_output=True, timeout=120)
    if how == "stdin":
        kwargs["input"] = b"some input"
    warm_proc, fresh = both([sys.executable, str(script), how, "x y"], **kwargs)
    assert_same(warm_proc, fresh)
    assert b"atexit ran" in fresh.stdout and b"thread ended" in fresh.stdout


def test_the_commands_refusals_and_help_are_the_same_bytes(tmp_path):
    for cmd in (
        [sys.executable, str(ROOT / "run_pets.py"), "--env", "nope"],
        [sys.executable, str(ROOT / "run_pets.py"), "--env", "invertedpendulum", "planner.horizon=0"],
        [sys.executable, "-m", "pets.collect", "--help"],
        [sys.executable, str(tmp_path / "missing.py")],
        [sys.executable, "-m", "pets.no_such_tool"],
        [sys.executable, "-m", "pets.compare", "offline", "--envs", "nope", "--out", str(tmp_path / "c")],
    ):
        warm_proc, fresh = both(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert_same(warm_proc, fresh)
        assert "Traceback" not in fresh.stderr and (fresh.returncode == 0) == ("--help" in cmd)


def test_a_short_run_gives_the_same_metrics(tmp_path):
    common = [
        sys.executable,
        str(ROOT / "run_pets.py"),
        "--env",
        "invertedpendulum",
        "--trials",
        "2",
        "--seed",
        "3",
        "--preset",
        "fast",
        *TINY_PLANNER,
        *TINY_MODEL,
        "threads=1",
        "--quiet",
    ]
    runs = [tmp_path / "warm", tmp_path / "fresh"]
    for runner, out in zip((warm.run, subprocess.run), runs):
        proc = runner([*common, "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
    rows = []
    for out in runs:
        with open(out / "metrics.csv", newline="") as f:
            rows.append(
                [{k: v for k, v in row.items() if not k.endswith(("_s", "_per_step"))} for row in csv.DictReader(f)]
            )
    assert rows[0] == rows[1] and len(rows[0]) == 2


def test_a_timeout_kills_the_child_and_raises_with_its_output(tmp_path):
    sleeper = tmp_path / "sleep.py"
    sleeper.write_text("import os, sys, time\nprint(os.getpid(), flush=True)\ntime.sleep(60)\n")
    start = time.monotonic()
    with pytest.raises(subprocess.TimeoutExpired) as caught:
        warm.run([sys.executable, str(sleeper)], capture_output=True, text=True, timeout=2)
    assert time.monotonic() - start < 30
    assert not alive(int(caught.value.stdout))


def test_what_a_fork_cannot_have_goes_to_a_fresh_process(tmp_path):
    (tmp_path / "x.py").write_text("")
    here = {"cwd": tmp_path}
    assert warm._forkable([sys.executable, "x.py"], {**here, "capture_output": True, "timeout": 5})
    assert not warm._forkable([sys.executable, "-c", "pass"], here)
    assert not warm._forkable(["/usr/bin/env", "python", "x.py"], here)
    assert not warm._forkable([sys.executable, "x.py"], {**here, "preexec_fn": print})
    assert not warm._forkable([sys.executable, "y.py"], here)  # Python's own "can't open file"
    assert not warm._forkable([sys.executable, "x.py"], {"cwd": tmp_path / "gone"})  # subprocess.run raises
    assert warm._startup_env({"OMP_NUM_THREADS": "1", "FOO": "x"}) == (("OMP_NUM_THREADS", "1"),)
    proc = warm.run([sys.executable, "-c", "import sys; print(sys.flags.optimize)"], capture_output=True, text=True)
    assert proc.stdout == "0\n"


def test_a_module_runs_in_a_main_namespace_like_a_fresh_ones(tmp_path):
    (tmp_path / "probe.py").write_text(
        "import sys\nprint(sys.argv, sorted(k for k in globals() if k != 'sys'), __file__)\n"
        "print(sorted(m for m in sys.modules if m.startswith('probe')))\n"
    )
    for args in (["-m", "probe", "a"], ["-m", "nope_no_such_module"]):
        warm_proc, fresh = both([sys.executable, *args], cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert_same(warm_proc, fresh)


def test_the_fresh_variable_runs_every_command_in_a_fresh_python(tmp_path, monkeypatch):
    (tmp_path / "parent.py").write_text("import os\nprint(os.getppid())\n")
    cmd = [sys.executable, str(tmp_path / "parent.py")]
    assert int(warm.run(cmd, capture_output=True, text=True).stdout) != os.getpid()  # a warm server's child
    monkeypatch.setenv(warm.FRESH_VARIABLE, "1")
    assert int(warm.run(cmd, capture_output=True, text=True).stdout) == os.getpid()


def test_each_child_draws_fresh_random_numbers_as_a_fresh_python_does(tmp_path):
    (tmp_path / "draw.py").write_text("import random, numpy, torch\nprint(random.random(), numpy.random.rand())\n"
                                      "print(torch.initial_seed())\n")  # fmt: skip
    cmd = [sys.executable, str(tmp_path / "draw.py")]
    first, second = (warm.run(cmd, capture_output=True, text=True).stdout.splitlines() for _ in range(2))
    assert first[0] != second[0] and first[1] != second[1]  # new entropy per process, as each fresh Python draws
