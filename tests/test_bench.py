"""The benchmark commands (pets.bench, pets.bench_train, pets.bench_layers) as a researcher runs them: bad input is
one line and exit 2 before any timing, a model of one's own (``imports=[...]``) is accepted as elsewhere, and the
figures name the machine and the command that made them."""

from __future__ import annotations

import json
import re
import shlex
import sys

import pytest
import torch

from tests import warm
from tests.test_cli import ROOT, error_lines
from tests.threads import one_thread

#: Small enough that a row times in well under a second.
TINY = [
    "--preset",
    "fast",
    "planner.population=8",
    "planner.particles=2",
    "planner.horizon=3",
    "planner.iterations=1",
    "model.hidden_size=16",
    "model.ensemble_size=2",
    "model.num_elites=1",
    "threads=1",
]


def test_bad_input_is_one_line_and_exit_2_before_any_timing(tmp_path):
    cases = [
        ("pets.bench", ["--repeats", "0"], "argument --repeats: must be an int >= 1, got '0'"),
        ("pets.bench", ["--model", "nosuch"], "--model must be one of delta, gem"),
        ("pets.bench", ["--env", "reacher", "--preset", "fast", "--json", tmp_path], "is a directory; give a file"),
        ("pets.bench_train", ["--epochs", "-1"], "argument --epochs: must be an int >= 1, got '-1'"),
        ("pets.bench_train", ["--model", "nosuch"], "--model must be one of delta, gem"),
        ("pets.bench_train", ["--env", "reacher", "--transitions", "5"], "--transitions 5 leaves no holdout rows"),
        ("pets.bench_layers", ["--repeats", "0"], "argument --repeats: must be an int >= 1"),
        ("pets.bench_layers", ["--rows", "8,-3"], "argument --rows: must be a comma list of ints >= 1"),
    ]
    if not torch.cuda.is_available():
        cases.append(("pets.bench_train", ["--env", "reacher", "device=cuda"], "torch sees no CUDA device"))
        cases.append(("pets.bench_train", ["--env", "reacher", "--device", "cuda"], "torch sees no CUDA device"))
    for module, args, fragment in cases:
        proc = warm.run([sys.executable, "-m", module, *map(str, args)], cwd=ROOT, capture_output=True, text=True,
                        timeout=120)  # fmt: skip
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], (module, args, proc.stderr[-2000:])
        assert not proc.stdout, (module, args, proc.stdout)  # nothing timed
    assert list(tmp_path.iterdir()) == []


def test_bench_names_the_machine_and_command_and_takes_your_own_model(tmp_path, monkeypatch, capsys):
    """A model of one's own (tests/own_planner.py's ``delta-mine``) is benchmarked as run_pets.py runs it; the
    output and the JSON name the CPU (model and bf16 ISA), threads, torch version and the command."""
    from pets import bench

    monkeypatch.chdir(ROOT)
    out = tmp_path / "b.json"
    argv = ["--env", "invertedpendulum", "--model", "delta-mine", "imports=[tests.own_planner]", "--repeats", "1"]
    with one_thread():  # the commands set torch's threads (threads=1, --threads 1): restored after
        assert bench.main([*argv, "--json", str(out), *TINY]) == 0
    printed = capsys.readouterr().out
    assert "invertedpendulum / delta-mine on cpu" in printed
    assert "machine: " in printed and "1 torch thread, torch " in printed
    assert "command: python -m pets.bench --env invertedpendulum --model delta-mine" in printed
    where = json.loads(out.read_text())["machine"]
    assert {"cpu", "cpus", "threads", "torch", "python", "command"} <= set(where)
    assert where["threads"] == 1 and where["torch"] == torch.__version__ and where["command"] in printed


def test_bench_train_and_bench_layers_name_the_machine(capsys):
    from dynamics import fused
    from pets import bench_layers, bench_train

    args = ["--env", "reacher", "--transitions", "100", "--epochs", "1", "--repeats", "1", *TINY]
    with one_thread():
        assert bench_train.main(args) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("machine: ") and "command: python -m pets.bench_train --env reacher" in printed
    assert "reacher / delta on " in printed and "bf16 / fp32: speed" in printed
    if not fused._AVAILABLE:
        pytest.skip("oneDNN has no fused bf16 linear here: pets.bench_layers refuses (test_precision.py)")
    with one_thread():
        assert bench_layers.main(["--rows", "4", "--repeats", "1"]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("machine: ") and "1 torch thread" in printed and "rows per member     4" in printed


def documented_bench_commands() -> list[tuple[str, str, list[str]]]:
    """``(file, tool, argv)`` of every ``python -m pets.bench`` / ``pets.bench_train`` line in the docs' bash blocks
    (as tests/test_docs_commands.py reads them: placeholders left out, comments cut)."""
    from tests.test_docs_commands import DOCS, PLACEHOLDER

    found = []
    for doc in DOCS:
        for block in re.findall(r"```bash\n(.*?)```", doc.read_text(), re.S):
            for line in block.replace("\\\n", " ").splitlines():
                start = re.match(r"\s*python -m pets\.(bench|bench_train) ", line)
                argv = shlex.split(line[start.end() :].split(" #")[0]) if start else []
                if start and not any(PLACEHOLDER.fullmatch(a) for a in argv):
                    found.append((doc.relative_to(ROOT).as_posix(), start.group(1), argv))
    return found


def test_the_documented_bench_commands_pass_their_checks(tmp_path, monkeypatch):
    """Every documented benchmark command parses and passes the checks made before any timing (config, memory,
    device, --json); a CUDA one is checked with --device cpu where torch sees no CUDA device."""
    from pets.tools import bench, bench_train

    commands = documented_bench_commands()
    assert len(commands) >= 4
    monkeypatch.chdir(tmp_path)  # a --json FILE is only probed, never written
    for doc, tool, argv in commands:
        if not torch.cuda.is_available():
            argv = [a if a != "cuda" else "cpu" for a in argv]
        try:
            {"bench": bench, "bench_train": bench_train}[tool]._arguments(argv)
        except SystemExit as exit_:
            pytest.fail(f"{doc}: python -m pets.{tool} {shlex.join(argv)}: exit {exit_.code}")
    assert list(tmp_path.iterdir()) == []
