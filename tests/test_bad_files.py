"""Binary files where text is expected (issue 55): a --config file and the CSV files of pets.compare headline are one
line naming the file and exit 2, never a UnicodeDecodeError traceback."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests import warm
from tests.test_cli import ROOT, cli, error_lines

BINARY = bytes(range(128, 256)) * 20


@pytest.fixture
def binary(tmp_path):
    path = tmp_path / "file.bin"
    path.write_bytes(BINARY)
    return path


def _compare(*args: object) -> subprocess.CompletedProcess:
    return warm.run(
        [sys.executable, "-m", "pets.compare", *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )


def _one_line(proc: subprocess.CompletedProcess, fragment: str) -> None:
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_binary_config_file_is_one_line(binary, tmp_path):
    proc = cli("--env", "reacher", "--config", binary, "--out", tmp_path / "run", check=False)
    _one_line(proc, "not a readable YAML")
    _one_line(_compare("online", "--envs", "reacher", "--trials", 1, "--config", binary), "not a readable YAML")


@pytest.mark.parametrize("option", ["--offline", "--relative", "--primary"])
def test_a_binary_csv_given_to_headline_is_one_line(binary, tmp_path, option):
    summary = ROOT / "docs" / "results" / "paper_ip_summary.csv"  # a good --offline file beside the binary one
    args = [option, binary] if option == "--offline" else ["--offline", summary, option, binary]
    _one_line(_compare("headline", *args, "--out", tmp_path / "h"), "not a text CSV file")


def test_a_run_whose_history_is_damaged_resumes_and_records_the_resume(tmp_path):
    """history.csv holding bytes that are not text (a damaged disk, a stray write) stopped ``--resume`` with a
    UnicodeDecodeError traceback (exit 1) before the run went on; the history only records the sessions: the run
    resumes, and the damaged rows are kept as they read, the resume row after them."""
    from pets.runs import rundir
    from tests.test_cli import TINY

    run = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--out", run, *TINY)
    (run / rundir.HISTORY_FILE).write_bytes(b"time,action,trials_done,host,pid,cpu\n" + BINARY + b"\n")
    proc = cli("--resume", run, "--trials", 2, check=False)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    history = rundir.read_history(run)
    assert (history[-1]["action"], history[-1]["trials_done"]) == ("resume", "1")
    assert len(rundir.read_metrics(run / rundir.METRICS_FILE)) == 2
