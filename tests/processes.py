"""Process states from Linux's /proc, for the tests that check that no process outlives its run; and the small
random data set that the subprocess tests train on."""

import sys
from pathlib import Path

from tests import warm


def children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (from /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def alive(pid: int) -> bool:
    """Whether ``pid`` is running (a zombie has exited)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds ``pid`` has used so far (0 once it is gone)."""
    import os

    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def default_sigint() -> None:
    """``preexec_fn`` of a child that a test interrupts: SIGINT back to its default, so the child's Python installs its
    KeyboardInterrupt handler even where the test process ignores SIGINT (an ignored signal is inherited through
    exec; libraries such as Ray change the test process's handlers)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def collect_random(out: Path, episodes: int) -> Path:
    """``out``: an InvertedPendulum data set of ``episodes`` random episodes, written by ``pets.collect`` itself."""
    argv = ["-m", "pets.collect", "--env", "invertedpendulum", "--policy", "random", "--episodes", str(episodes)]
    root = Path(__file__).resolve().parents[1]
    cmd = [sys.executable, *argv, "--threads", "1", "--out", str(out), "--quiet"]
    warm.run(cmd, cwd=root, check=True, capture_output=True, timeout=300)
    return out
