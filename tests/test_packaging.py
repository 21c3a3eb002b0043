"""``pip install .`` outside the source tree: the wheel built from pyproject.toml, installed with ``--no-deps`` into
a venv that sees this environment's packages, runs its commands and every docs/api.md example from another
directory, importing the venv's copy (not the source tree, not the editable install). It is the suite's one run of
docs/api.md's examples: they run as written, in order, and what they make is checked."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from tests.tiny import TINY_MODEL, TINY_PLANNER

ROOT = Path(__file__).resolve().parents[1]
#: What the build reads: the metadata, the README and LICENSE it names, and the code (nothing else is copied).
BUILD_INPUTS = (
    "pyproject.toml",
    "setup.py",
    "README.md",
    "LICENSE",
    "run_pets.py",
    "pets",
    "gem_head",
    "envs",
    "dynamics",
)


#: Appended to docs/api.md's examples: what they must have made (their objects, by name), one line when all hold.
EXAMPLES_MADE = """
assert agent.trials_done == 2 and same.trials_done == 3 and len(rewards) == 2, (agent, same, rewards)
assert isinstance(next_obs, np.ndarray) and next_obs.shape == (8, 10), type(next_obs)
assert path.shape == (8, 10, 10), path.shape
print("what the examples made: as documented")
"""


def run(*cmd: str | Path, cwd: Path, env: dict[str, str] | None = None) -> str:
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"{cmd}: exit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    return proc.stdout


def test_the_wheel_installs_and_runs_outside_the_source_tree(tmp_path):
    src = tmp_path / "src"  # a copy, so the build's build/ and egg-info never touch (or come from) the checkout
    src.mkdir()
    for name in BUILD_INPUTS:
        copy = shutil.copytree if (ROOT / name).is_dir() else shutil.copy2
        copy(
            ROOT / name,
            src / name,
            **({"ignore": shutil.ignore_patterns("__pycache__")} if copy is shutil.copytree else {}),
        )
    run(
        sys.executable,
        "-m",
        "pip",
        "wheel",
        ".",
        "--no-deps",
        "--no-build-isolation",
        "-q",
        "-w",
        tmp_path / "dist",
        cwd=src,
    )
    (wheel,) = (tmp_path / "dist").glob("gem_pets-*.whl")
    venv = tmp_path / "venv"
    run(sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", venv, cwd=tmp_path)
    python = venv / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the tests' own path would win otherwise
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    # The venv has no pip of its own: the system's, seen through --system-site-packages, installs into the venv.
    # --ignore-installed: the environment's own gem-pets (an editable install of the checkout) would otherwise count
    # as "already installed" and nothing would be installed; it is not uninstalled either.
    run(
        python,
        "-m",
        "pip",
        "install",
        "--no-deps",
        "--no-index",
        "--ignore-installed",
        "-q",
        wheel,
        cwd=tmp_path,
        env=env,
    )

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = run(
        python,
        "-c",
        "import pets, run_pets, envs; print(pets.__file__, run_pets.__file__, envs.__file__)",
        cwd=elsewhere,
        env=env,
    )
    site = (venv / "lib").resolve()
    for path in where.split():
        assert Path(path).resolve().is_relative_to(site), f"{path} is not the venv's copy (site-packages under {site})"
        assert not Path(path).resolve().is_relative_to(ROOT)

    assert run(python, "-m", "pets.train", "--help", cwd=elsewhere, env=env).startswith("usage: pets.train")
    tiny = [*TINY_PLANNER, *TINY_MODEL, "episode_length=30", "seed_steps=100", "threads=1"]
    out = run(
        venv / "bin" / "run-pets",
        "--env",
        "reacher",
        "--model",
        "gem",
        "--trials",
        "1",
        "--out",
        "run",
        "--quiet",
        *tiny,
        cwd=elsewhere,
        env=env,
    )
    assert out.startswith("done: 1 trials") and (elsewhere / "run" / "checkpoint.pt").is_file()

    # every docs/api.md example, as written and in order (they build on each other), with the installed package (the
    # suite's one run of them), then what they must have made
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "api.md").read_text(), re.S)
    assert len(blocks) >= 3
    (elsewhere / "examples.py").write_text("\n".join([*blocks, EXAMPLES_MADE]))
    out = run(python, "examples.py", cwd=elsewhere, env=env)
    assert (
        out.startswith("PETS(env='reacher', model='gem', trials_done=2")
        and "10 MPC steps: reward" in out
        and out.rstrip().endswith("what the examples made: as documented")
        and (elsewhere / "runs" / "reacher-gem-api" / "checkpoint.pt").is_file()
    )
