"""docs/scripts/run_queue.sh, the background queue the studies run from: each kind resumes or skips as its
header says, a finished command never runs again, and a SAC collection's CPU seconds add up every measured
segment (none is written where a segment went unmeasured). A stand-in ``python`` on PATH records its calls."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

QUEUE = Path(__file__).resolve().parents[1] / "docs" / "scripts" / "run_queue.sh"

# The stand-in: logs its arguments, burns a little CPU for a collection, and fails a collection's first segment
# (a crash it resumes from) unless told otherwise; the real queue measures and books it.
FAKE_PYTHON = r"""#!/usr/bin/env bash
echo "$*" >> "$CALLS"
if [[ $1 == -m && $2 == pets.collect ]]; then
  for ((i = 0; i < 300000; i++)); do :; done
  n=$(grep -c pets.collect "$CALLS")
  ((n < ${SAC_OK_FROM:-2})) && exit 3
  for ((j = 1; j <= $#; j++)); do [[ ${!j} == --out ]] && k=$((j + 1)) && touch "${!k}"; done
fi
exit 0
"""


@pytest.fixture()
def queue(tmp_path: Path):
    """Run the queue on a job file in ``tmp_path`` with the stand-in python first on PATH; returns the calls."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    (bindir / "python").write_text(FAKE_PYTHON)
    (bindir / "python").chmod(0o755)
    calls = tmp_path / "calls.txt"

    def run(lines: list[str], **env: str) -> list[str]:
        jobs = tmp_path / "q.jobs"
        jobs.write_text("\n".join(lines) + "\n")
        environ = {**os.environ, "PATH": f"{bindir}:{os.environ['PATH']}", "CALLS": str(calls), **env}
        subprocess.run(["bash", str(QUEUE), str(jobs)], check=True, env=environ, timeout=120)
        return calls.read_text().splitlines() if calls.exists() else []

    return run


def test_a_pets_job_starts_then_resumes_from_its_checkpoint(tmp_path, queue):
    out = tmp_path / "run-a"
    job = f"{tmp_path}|{out}|pets|--env hopper --seed 3 threads=1"
    assert queue([job]) == [f"run_pets.py --env hopper --seed 3 threads=1 --out {out} --quiet"]
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"")
    assert queue([job])[-1] == f"run_pets.py --resume {out} --quiet"


def test_a_finished_command_is_marked_done_and_never_runs_again(tmp_path, queue):
    count = tmp_path / "count"
    ok = f"{tmp_path}|{tmp_path / 'ok'}|cmd|echo ran >> {count}"
    failing = f"{tmp_path}|{tmp_path / 'bad'}|cmd|echo tried >> {count}; false"
    queue([ok, failing])
    queue([ok, failing])
    assert count.read_text().split() == ["ran", "tried", "tried"]
    assert (tmp_path / "ok.done").exists() and not (tmp_path / "bad.done").exists()


def test_sac_cpu_seconds_add_up_every_segment(tmp_path, queue):
    out = tmp_path / "sac-hopper-s0"
    job = f"{tmp_path}|{out}|sac|--env hopper --policy sac:100 --seed 0"
    queue([job])  # the first segment fails (the stand-in's crash): measured, nothing booked yet
    assert not Path(f"{out}.cpu_s").exists()
    calls = queue([job])  # the second finishes
    segments = Path(f"{out}.segments").read_text().split()
    assert segments[0::2] == ["start", "start"]
    seconds = [float(s) for s in segments[1::2]]
    assert all(s > 0 for s in seconds)
    assert float(Path(f"{out}.cpu_s").read_text()) == pytest.approx(sum(seconds))
    assert queue([job]) == calls  # the data set exists: skipped


def test_sac_cpu_is_left_unknown_when_a_segment_went_unmeasured(tmp_path, queue):
    out = tmp_path / "sac-hopper-s1"
    Path(f"{out}.segments").write_text("start\n")  # a segment killed together with its queue
    queue([f"{tmp_path}|{out}|sac|--env hopper --policy sac:100 --seed 1"], SAC_OK_FROM="1")
    assert Path(f"{out}.npz").exists()
    assert not Path(f"{out}.cpu_s").exists()


def test_an_unknown_kind_is_logged_and_skipped(tmp_path, queue):
    assert queue([f"{tmp_path}|{tmp_path / 'x'}|slurm|whatever"]) == []
    assert "unknown kind 'slurm'" in (tmp_path / "logs" / "x.log").read_text()
