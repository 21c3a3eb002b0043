"""The front door (issue 55): the README's first command installs the CPU build of torch and starts a run that a CPU
finishes in minutes, saying its preset and device; the research config is the default without --preset fast; a
--config file's precedence over --preset and --env is said in one line; run_pets.py takes pets.compare's spellings
(model=NAME, --threads); the README's Python block runs as written and its metrics.csv column list is the file's."""

from __future__ import annotations

import os
import re
import shlex
import sys

import numpy as np
import torch

from pets.runs import rundir
from tests import warm
from tests.test_cli import ROOT, TINY, cli, error_lines
from tests.threads import one_thread

README = (ROOT / "README.md").read_text()


def _first_command() -> list[str]:
    block = re.search(r"```bash\n(.*?)```", README, re.S).group(1)
    return [shlex.split(part) for part in block.strip().split("&&")]


def test_the_first_command_installs_cpu_torch_and_runs_the_cpu_preset_on_one_thread():
    install, _, run = _first_command()
    assert (
        install[:3] == ["pip", "install", "torch==2.13.0"]
        and install[install.index("--extra-index-url") + 1] == "https://download.pytorch.org/whl/cpu"
    )
    assert run[:2] == ["python", "run_pets.py"] and "--preset" in run and run[run.index("--preset") + 1] == "fast"
    assert run[run.index("--model") + 1] == "gem" and run[run.index("--env") + 1] == "halfcheetah"  # the main job
    assert "threads=1" in run
    proc = cli(*run[2:], "--print-config")
    assert "planner:" in proc.stdout and "threads: 1" in proc.stdout


def test_ci_runs_the_readmes_test_command():
    """.ci/run installs and tests exactly as the README's second command says (each of its '&&' parts a line)."""
    second = re.findall(r"```bash\n(.*?)```", README, re.S)[1].strip()
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    parts = [part.strip() for part in second.split("&&")]
    assert all(part in ci for part in parts), [part for part in parts if part not in ci]
    assert ci.index(parts[0]) < ci.index(parts[1]) < ci.index(parts[2])


def test_the_start_line_states_preset_and_device_and_warns_of_research_on_a_cpu(tmp_path):
    proc = cli("--env", "invertedpendulum", "--trials", 1, "--out", tmp_path / "fast", *TINY)
    auto = "cuda" if torch.cuda.is_available() else "cpu"  # device auto
    assert f"run directory: {tmp_path / 'fast'} (preset fast on {auto})" in proc.stderr
    feedback = ["planner.candidates=feedback", "planner.feedback.features=[0,99]", "planner.replan_every=1"]
    proc = cli("--env", "halfcheetah", "--device", "cpu", "--out", tmp_path / "research", *feedback, check=False)
    assert "(preset research on cpu; the PETS papers' planner, slow on a CPU: --preset fast" in proc.stderr


def test_a_config_file_over_a_preset_or_another_env_is_said_in_one_line(tmp_path):
    reacher = tmp_path / "reacher.yaml"
    reacher.write_text(cli("--env", "reacher", "--model", "gem", "--print-config").stdout)
    proc = cli("--config", reacher, "--env", "halfcheetah", "--preset", "fast", "--print-config")
    notes = [line for line in proc.stderr.splitlines() if "note:" in line]
    assert len(notes) == 2
    assert "replaces" in notes[0] and "of --preset fast" in notes[0] and "--config file < flags" in notes[0]
    assert "was written for env reacher" in notes[1] and "--env halfcheetah" in notes[1]
    assert "horizon: 15" in proc.stdout  # the rule: the file wins over the preset and the env's defaults


def test_run_pets_takes_model_equals_name_and_threads_flag_and_says_what_model_dot_is():
    proc = cli("--env", "reacher", "model=gem", "--threads", 1, "--print-config")
    assert "head: gem" in proc.stdout and "threads: 1" in proc.stdout
    proc = cli("--env", "reacher", "model=nope", "--print-config", check=False)
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and "model.* keys set the network" in lines[0]
    assert "package.module:ATTR" in cli("--help").stdout


def test_the_readmes_python_block_runs_as_written(tmp_path, monkeypatch):
    block = re.search(r"## From Python\n\n```python\n(.*?)```", README, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    with one_thread():
        exec(compile(block, "README.md", "exec"), namespace)
    assert namespace["agent"].trials_done == 1 and np.asarray(namespace["action"]).shape == (1,)
    assert (tmp_path / "runs" / "my-run" / "checkpoint.pt").is_file()


def test_the_documented_metrics_columns_are_the_files():
    """docs/cli.md ("Reading results", linked from the README) lists metrics.csv's columns as the file has them."""
    cli_doc = (ROOT / "docs" / "cli.md").read_text()
    listed = re.search(r"`metrics.csv`: one row per trial: `([^`]*)`", cli_doc).group(1)
    assert [c.strip() for c in listed.replace("\n", " ").split(",")] == rundir.METRIC_COLUMNS


def test_pets_compare_takes_run_pets_spellings_env_model_seed_and_threads(tmp_path):
    args = ["--env", "invertedpendulum", "--model", "delta", "--seed", "0", "--trials", "1", "threads=2"]
    proc = warm.run(
        [sys.executable, "-m", "pets.compare", "online", *args, "--out", str(tmp_path), "--quiet", *TINY[:-2]],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 0, proc.stderr
    config = (tmp_path / "runs" / "invertedpendulum-delta-s0" / "config.yaml").read_text()
    assert "head: delta" in config and "threads: 2" in config
