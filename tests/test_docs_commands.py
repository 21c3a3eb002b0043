"""Every ``pets.compare online|offline`` and ``run_pets.py`` command in the bash blocks of README.md and docs/ is true
today: it parses and resolves every run's config (``--print-config``: nothing is run or written). Left out: the
dated history (docs/results_history.md: what was run then), commands with placeholders (``ENV``, ``N``, ``$VAR``,
``<...>``) and ``--resume`` (it reads a run directory)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import torch

import run_pets
from pets.experiments.cli import main as compare_main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").rglob("*.md") if p.name != "results_history.md")]
PROGRAMS = {"python -m pets.compare": compare_main, "python run_pets.py": run_pets.main}
#: The lines that start one of them (pets.compare's online and offline modes: the ones that make run configs).
STARTS = re.compile(r"\s*(python -m pets\.compare(?= (?:online|offline) )|python run_pets\.py(?= ))")
PLACEHOLDER = re.compile(r"[A-Z][A-Z0-9_]*(,[A-Z][A-Z0-9_]*)*|.*[$<].*")


def documented_commands() -> list[tuple[str, str, list[str]]]:
    """``(file, program, argv)`` of every such command, its line continuations joined and its comment cut."""
    found = []
    for doc in DOCS:
        for block in re.findall(r"```bash\n(.*?)```", doc.read_text(), re.S):
            for line in block.replace("\\\n", " ").splitlines():
                start = STARTS.match(line)
                if start is None:
                    continue
                program = start.group(1)
                argv = shlex.split(line[start.end() :].split(" #")[0].split(" && ")[0])
                if "--resume" not in argv and not any(PLACEHOLDER.fullmatch(a) for a in argv):
                    found.append((doc.relative_to(ROOT).as_posix(), program, argv))
    return found


COMMANDS = documented_commands()


def test_the_docs_hold_commands_to_check():
    assert len(COMMANDS) >= 30 and {p for _, p, _ in COMMANDS} == set(PROGRAMS)


@pytest.mark.parametrize(("doc", "program", "argv"), COMMANDS, ids=[f"{d}:{i}" for i, (d, _, _) in enumerate(COMMANDS)])
def test_a_documented_command_resolves_its_configs(doc, program, argv, monkeypatch, capsys):
    monkeypatch.chdir(ROOT)  # where the docs' commands run (a user's env module as tests.custom_envs:ATTR)
    if "cuda" in argv and not torch.cuda.is_available():  # its device check refuses here: checked on CPU
        argv = [a if a != "cuda" else "cpu" for a in argv]
    try:
        code = PROGRAMS[program]([*argv, "--print-config"])
    except SystemExit as exit_:
        code = exit_.code
    err = capsys.readouterr().err
    assert code == 0, f"{doc}: {program} {shlex.join(argv)}\n{err}"
