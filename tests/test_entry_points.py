"""The console scripts named in pyproject.toml: each resolves to a callable that runs its command from ``sys.argv``
(as ``python -m`` does, pets/tools/console.py), and its ``--help`` exits 0."""

import importlib
import signal
import subprocess
import sys
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the dev extra installs tomli
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


def console_scripts() -> dict[str, str]:
    """``{name: "module:function"}`` of ``[project.scripts]`` in pyproject.toml (read, not run)."""
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


SCRIPTS = console_scripts()


def test_every_command_has_a_console_script():
    assert set(SCRIPTS) >= {
        "run-pets",
        "pets-compare",
        "pets-collect",
        "pets-train",
        "pets-evaluate",
        "pets-openloop",
        "pets-onestep",
        "pets-bench",
    }


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_console_script_resolves_and_its_help_exits_0(name, capsys, monkeypatch):
    module, function = SCRIPTS[name].split(":")
    script = getattr(importlib.import_module(module), function)
    monkeypatch.setattr(sys, "argv", [name, "--help"])
    # run_command ignores Ctrl-C and SIGTERM once the command is over: this process gets its handlers back
    handlers = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        with pytest.raises(SystemExit) as exit_info:
            script()
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
    assert exit_info.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_python_m_pets_compare_still_runs_the_comparison_cli():
    proc = subprocess.run(
        [sys.executable, "-m", "pets.compare", "online", "--help"], cwd=ROOT, capture_output=True, text=True
    )
    assert proc.returncode == 0 and proc.stdout.startswith("usage: pets.compare online")


@pytest.mark.parametrize("tool", ["collect", "evaluate", "openloop", "visualize", "bench_layers"])
@pytest.mark.parametrize("value", ["-1", "two"])
def test_the_tools_threads_option_is_one_check_in_one_line(tool, value, capsys):
    """``--threads`` of every tool that takes it is pets.tools.cli's (one type, one message), checked before the
    tool reads any other argument."""
    main = importlib.import_module(f"pets.tools.{tool}").main
    with pytest.raises(SystemExit) as exit_info:
        main(["--threads", value, "x"])
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert (
        exit_info.value.code == 2
        and f"argument --threads: must be an int >= 0 (0: torch's default), got '{value}'" in line
    )


def test_a_reader_that_goes_away_early_ends_a_command_quietly_and_another_broken_pipe_is_not_hidden():
    """``run_pets.py --print-config | head -1``: the reader of stdout is gone before the command writes; no
    traceback, exit 1 (as Python's documentation does on EPIPE). A broken pipe that is not stdout's (a child's, a
    socket) is the command's own failure: it is not silenced."""
    proc = subprocess.Popen(
        [sys.executable, "run_pets.py", "--env", "halfcheetah", "--print-config"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()  # before the command has imported anything: its first write meets a closed pipe
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 1 and err == ""
    other = "from pets.tools.cli import run_command\ndef main():\n    raise BrokenPipeError(32, 'a child went away')\n"
    other += "run_command('x', main)\n"
    done = subprocess.run([sys.executable, "-c", other], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "BrokenPipeError: [Errno 32] a child went away" in done.stderr
