"""Where the test suite's time goes: runs the README's test command with ``--durations=0`` and logs every Python
process it starts (CPU seconds at exit, its command line), then prints the wall time, the ten costliest test files,
the costliest tests, the subprocesses' CPU per command (how much of it is Python's and torch's start-up) and how
busy the cores were.

    python docs/scripts/suite_profile.py [--log-dir DIR] [-- PYTEST_ARGS...]

The process log works through a ``usercustomize`` module placed in Python's user site-packages for the run and
removed afterwards (every child Python loads it, whatever PYTHONPATH a test gives it); processes killed by a
signal or ending by ``os._exit`` write no line. Run it on an idle machine: the figures are CI's only when nothing
else runs (pause background runs with ``kill -STOP``, ``kill -CONT`` after)."""

from __future__ import annotations

import argparse
import collections
import os
import re
import site
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HOOK = """import os
_suite_profile_log = os.environ.get("SUITE_PROFILE_LOG")
if _suite_profile_log:  # read now: a process may change its environment (tests/warm.py's forks replace it)
    import atexit, sys
    def _suite_profile_line():
        t = os.times()
        try:
            with open(_suite_profile_log, "a") as f:
                f.write(f"{os.getpid()}\\t{t.user + t.system:.2f}\\t{' '.join(sys.argv)[:200]}\\n")
        except OSError:
            pass
    atexit.register(_suite_profile_line)
"""
DURATION = re.compile(r"([\d.]+)s (call|setup|teardown)\s+(tests/\S+?\.py)::(\S+)")


def cpu_jiffies() -> tuple[int, int]:
    """The machine's busy and idle clock ticks since boot, all cores (``/proc/stat``'s first line)."""
    fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle, iowait
    return sum(fields) - idle, idle


def command_name(argv: str) -> str:
    """A process's command for grouping: the script's file name or ``-m MODULE`` (``-c`` for pytest's workers and
    multiprocessing's children)."""
    words = argv.split()
    if not words:
        return "?"
    if words[0] == "-m" and len(words) > 1:
        return f"-m {words[1]}"
    return words[0].rsplit("/", 1)[-1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--log-dir", type=Path, default=Path("suite-profile"), help="where the two logs are written")
    p.add_argument("pytest_args", nargs="*", help="after --: pytest's arguments (default: the README's)")
    args = p.parse_args()
    pytest_args = args.pytest_args or ["-q", "-n", "2", "--dist", "loadfile", "tests"]
    args.log_dir.mkdir(parents=True, exist_ok=True)
    durations, processes = args.log_dir / "durations.log", args.log_dir / "processes.tsv"
    processes.unlink(missing_ok=True)
    user_site = Path(site.getusersitepackages())
    hook = user_site / "usercustomize.py"
    if hook.exists():
        p.error(f"{hook} exists already; move it away first (this script writes and removes its own)")
    user_site.mkdir(parents=True, exist_ok=True)
    hook.write_text(HOOK)
    try:
        start, before = time.monotonic(), cpu_jiffies()
        with durations.open("w") as out:
            code = subprocess.call(
                [sys.executable, "-m", "pytest", *pytest_args, "--durations=0"],
                cwd=ROOT,
                stdout=out,
                stderr=subprocess.STDOUT,
                env={**os.environ, "SUITE_PROFILE_LOG": str(processes.resolve())},
            )
        wall = time.monotonic() - start
        busy, idle = (a - b for a, b in zip(cpu_jiffies(), before))
    finally:
        hook.unlink()
    report(durations, processes, wall)
    print(f"\nthe machine's cores were busy {100 * busy / (busy + idle):.0f} % of the run (idle: room for a worker)")
    return code


def report(durations: Path, processes: Path, wall: float) -> None:
    files: collections.Counter[str] = collections.Counter()
    tests: list[tuple[float, str]] = []
    lines = durations.read_text().strip().splitlines()
    for line in lines:
        m = DURATION.match(line)
        if m:
            files[m.group(3)] += float(m.group(1))
            tests.append((float(m.group(1)), f"{m.group(2)} {m.group(3)}::{m.group(4)}"))
    print(f"wall {wall:.0f} s; the tests' durations add up to {sum(files.values()):.0f} s; last line:")
    print("   ", lines[-1])
    print("\ncostliest test files (s):")
    for name, s in files.most_common(10):
        print(f"  {s:7.1f}  {name}")
    print("\ncostliest tests (s):")
    for s, name in sorted(tests, reverse=True)[:15]:
        print(f"  {s:7.1f}  {name}")
    cpu: collections.Counter[str] = collections.Counter()
    count: collections.Counter[str] = collections.Counter()
    rows = [line.split("\t") for line in processes.read_text().splitlines()] if processes.exists() else []
    for _, seconds, argv in rows:
        cpu[command_name(argv)] += float(seconds)
        count[command_name(argv)] += 1
    print(f"\n{len(rows)} Python processes logged, {sum(cpu.values()):.0f} CPU-s (pytest's workers are '-c'):")
    for name, s in cpu.most_common(12):
        print(f"  {s:7.1f} CPU-s  {count[name]:4d} x  {name}")


if __name__ == "__main__":
    sys.exit(main())
