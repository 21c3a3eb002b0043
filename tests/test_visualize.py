"""MuJoCo rendering: the headless GL backend, observations back to qpos (against the simulator), the trajectory
grid of pets.visualize (real renders of the truth and of real trained models, read back from the PNG)."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

import envs
from envs.render import Renderer, qpos_from_obs, select_gl_backend
from pets import visualize
from pets.data.collect import collect
from pets.data.datasets import save_dataset
from pets.learning.offline import train_offline
from tests.tiny import TINY_MODEL

ROOT = Path(__file__).resolve().parents[1]
SIZE = (64, 48)  # panel width, height
STEPS = [0, 5, 15]
OWN_ENV = "tests.custom_envs:PENDULUM"  # your own env, not MuJoCo


def test_gl_backend_is_chosen_only_when_unset_and_headless():
    assert select_gl_backend({"MUJOCO_GL": "glfw"}) == "glfw"
    assert select_gl_backend({"DISPLAY": ":0"}) is None
    environ: dict[str, str] = {}
    chosen = select_gl_backend(environ)
    assert chosen in ("egl", "osmesa") and environ["MUJOCO_GL"] == chosen


def test_import_envs_sets_a_backend_that_renders_headless():
    """A fresh process with no display and no MUJOCO_GL: ``import envs`` picks the backend, MuJoCo renders."""
    code = (
        "import os, envs; from envs.render import Renderer; import numpy as np\n"
        "spec = envs.get('halfcheetah'); r = Renderer(spec, 64, 48); env = spec.make(); obs, _ = env.reset(seed=0)\n"
        "f = r.frame(env.unwrapped.data.qpos.copy()); print(os.environ['MUJOCO_GL'], f.shape, int(f.std() > 5))"
    )
    environ = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY")}
    environ["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    backend, *rest = out.stdout.split()
    assert backend in ("egl", "osmesa") and " ".join(rest) == "(48, 64, 3) 1"


@pytest.mark.parametrize("name", envs.names())
def test_qpos_from_obs_is_the_simulators_qpos_and_renders(name):
    spec = envs.get(name)
    env = spec.make()
    obs, _ = env.reset(seed=1)
    rng = np.random.default_rng(0)
    with Renderer(spec, *SIZE) as renderer:
        for _ in range(15):
            obs, *_ = env.step(rng.uniform(spec.action_low, spec.action_high))
        data = env.unwrapped.data
        qpos = qpos_from_obs(spec, obs, renderer.model.nq)
        diff = qpos - data.qpos
        # hinges given as cos/sin come back in (-pi, pi]: equal up to whole turns
        assert np.allclose(np.angle(np.exp(1j * diff)), 0, atol=1e-6), diff
        frame = renderer.frame(qpos)
        simulator = renderer.frame(data.qpos.copy())
        first = renderer.frame(qpos_from_obs(spec, env.reset(seed=1)[0], renderer.model.nq))
    env.close()
    assert frame.shape == (SIZE[1], SIZE[0], 3) and frame.dtype == np.uint8
    assert frame.std() > 5, "blank frame"
    assert np.abs(frame.astype(int) - simulator).max() <= 1  # the observation draws the simulator's own qpos
    assert np.abs(frame.astype(int) - first).mean() > 0.5  # 15 steps later the picture has changed


@pytest.fixture(scope="module")
def runs(tmp_path_factory, request):
    """Per env: a data set of 2 smooth-random episodes and a model trained 2 epochs on it (deliberately wrong)."""
    made = {}
    for name in ("halfcheetah", "ant"):
        work = tmp_path_factory.mktemp(name)
        data = save_dataset(work / "data.npz", collect(envs.get(name), "smooth-random", 2, seed=0, max_steps=40))
        overrides = dict(item.split("=") for item in TINY_MODEL) | {"threads": "1", "model.max_epochs": "1"}
        run = train_offline(data, "delta", work / "run", overrides, preset="fast", seed=0)
        made[name] = (data, run)
    return made


@pytest.mark.parametrize("name", ["halfcheetah", "ant"])  # a planar env and an SO(3) one
def test_grid_truth_vs_a_wrong_model(runs, tmp_path, name):
    data, run = runs[name]
    out = tmp_path / "grid.png"
    result = visualize.visualize([run, run], data, out, STEPS, size=SIZE, labels=["wrong", "wrong again"])
    frames = result["frames"]
    assert frames.shape == (3, len(STEPS), SIZE[1], SIZE[0], 3)
    image = iio.imread(out)
    width, height = result["size"]
    lines = len(visualize.wrap_caption(result["caption"], width))
    assert image.shape[:2] == (height, width) == visualize.figure_size(3, len(STEPS), *SIZE, lines)[::-1]
    assert width == visualize.LABEL_W + len(STEPS) * SIZE[0]
    for r in range(3):  # the panels in the PNG are the rendered frames, unscaled
        for c in range(len(STEPS)):
            top, left = visualize.TITLE_H + r * SIZE[1], visualize.LABEL_W + c * SIZE[0]
            panel = image[top : top + SIZE[1], left : left + SIZE[0], :3].astype(int)
            assert panel.std() > 5, f"blank panel {r}, {c}"
            assert np.array_equal(panel, frames[r, c])
    assert np.array_equal(frames[0, 0], frames[1, 0])  # step 0: the same start state in every row
    for c in range(1, len(STEPS)):
        assert np.abs(frames[0, c].astype(int) - frames[1, c]).mean() > 1, f"truth = wrong model at step {STEPS[c]}"
    assert np.array_equal(frames[1], frames[2])  # the same run twice: the same (mean) prediction
    assert result["labels"] == ["truth", "wrong", "wrong again"]
    assert ("Root x, y" if name == "ant" else "Root x") in result["caption"]


def test_the_caption_names_the_seed_of_sampled_predictions(runs, tmp_path):
    """--mode sample draws with --seed: the caption says which, as it says the data, episode and start."""
    data, run = runs["halfcheetah"]
    result = visualize.visualize([run], data, tmp_path / "s.png", [0, 3], mode="sample", seed=7, size=SIZE)
    assert "open-loop predictions (sample, seed 7) with the recorded actions" in result["caption"]


def test_grid_with_the_truths_root_and_the_cli(runs, tmp_path, capsys):
    data, run = runs["halfcheetah"]
    out = tmp_path / "fig.png"
    code = visualize.main(
        ["--runs", str(run), "--data", str(data), "--env", "HalfCheetah-v5", "--steps", "0,3", "--size", "64x48"]
        + ["--root", "truth", "--threads", "1", "--out", str(out)]
    )
    assert code == 0 and iio.imread(out).shape[1] == visualize.LABEL_W + 2 * 64
    assert "2 rows x 2 steps" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--labels", ""], "--labels has an empty name: ''"),  # was a row without a name
        (["--steps", "0,100"], "episode 0 has 40 steps"),
        (["--steps", "0,-1"], "--steps must be"),
        (["--env", "ant"], "does not match the data set"),
        (["--size", "10x10"], "--size must be"),
        (["--labels", "a,b"], "--labels has 2 names for 1 runs"),
        (["--episode", "5"], "--episode must be in [0, 1]"),
        (["--start", "-1"], "--start must be >= 0 (a step of the episode), got -1"),  # was said to exceed the episode
    ],
)
def test_bad_input_is_one_line_exit_2(runs, tmp_path, capsys, extra, message):
    data, run = runs["halfcheetah"]
    with pytest.raises(SystemExit) as exit_info:
        visualize.main(["--runs", str(run), "--data", str(data), "--out", str(tmp_path / "f.png"), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "f.png").exists()


def test_out_that_is_a_directory_is_one_line_exit_2_before_any_work(runs, tmp_path, capsys):
    """Was a traceback (IsADirectoryError, exit 1) after the models had run and the frames were rendered."""
    data, run = runs["halfcheetah"]
    (tmp_path / "f.png").mkdir()
    with pytest.raises(SystemExit) as exit_info:
        visualize.main(["--runs", str(run), "--data", str(data), "--out", str(tmp_path / "f.png")])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and err == [
        f"pets.visualize: error: --out {tmp_path / 'f.png'} is a directory; give a file name"
    ]


def test_a_failed_write_is_one_line_exit_3(runs, tmp_path, capsys, monkeypatch):
    """A full disk while the PNG is written: one line naming the file, exit 3 (was a traceback, exit 1)."""
    data, run = runs["halfcheetah"]

    def full_disk(path: Path, data: bytes) -> None:
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(visualize, "atomic_write_bytes", full_disk)
    out = tmp_path / "f.png"
    argv = ["--runs", str(run), "--data", str(data), "--steps", "0,3", "--size", "64x48", "--out", str(out)]
    with pytest.raises(SystemExit) as exit_info:
        visualize.main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 3 and len(err) == 1, err
    assert f"writing {out} failed (No space left on device); no figure was written" in err[0]


def test_a_data_set_of_your_own_env_is_refused_in_one_line(tmp_path, capsys):
    """``module:ATTR`` envs have no camera and no known qpos: one line, exit 2, before any model is loaded (was a
    traceback: KeyError for a MuJoCo env, AttributeError for another)."""
    data = save_dataset(tmp_path / "own.npz", collect(envs.get(OWN_ENV), "random", 1, seed=0, max_steps=5))
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(f"env: {OWN_ENV}\n")  # never read: the data set's env is refused first
    with pytest.raises(SystemExit) as exit_info:
        visualize.main(["--runs", str(run), "--data", str(data), "--steps", "0,1", "--out", str(tmp_path / "f.png")])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1, err
    assert f"the data set is from your own env {OWN_ENV}: pets.visualize draws the catalogue envs only" in err[0]
    assert not (tmp_path / "f.png").exists()


def test_your_own_mujoco_env_renders_with_mujocos_default_camera():
    """Videos of your own MuJoCo env (``run_pets.py --video``): no camera in CAMERAS, so MuJoCo's default free camera
    (was a KeyError traceback)."""
    ip = envs.get("invertedpendulum")
    spec = envs.custom_spec("my-pendulum", "InvertedPendulum-v5", ip.layout, ip.reward, ip.terminated)
    env = spec.make()
    env.reset(seed=0)
    with Renderer(spec, *SIZE, model=env.unwrapped.model, effects=False) as renderer:
        frame = renderer.frame_of(env.unwrapped.data)
    env.close()
    assert frame.shape == (SIZE[1], SIZE[0], 3) and frame.std() > 5


def test_the_documented_command_renders_headless(runs, tmp_path):
    """``python -m pets.visualize`` in a fresh process with no display and no MUJOCO_GL (the suite's own is set by
    ``import envs``): the command picks the backend before mujoco is imported (mujoco reads it once, on import)."""
    data, run = runs["halfcheetah"]
    environ = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY")}
    environ.update(PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    out = tmp_path / "f.png"
    args = ["--runs", str(run), "--data", str(data), "--steps", "0,3", "--size", "64x48", "--out", str(out)]
    proc = subprocess.run(
        [sys.executable, "-m", "pets.visualize", *args], env=environ, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert iio.imread(out).shape[1] == visualize.LABEL_W + 2 * 64


def test_a_mujoco_gl_that_mujoco_cannot_load_is_one_line_exit_2(tmp_path):
    """``import mujoco`` loads the backend of a MUJOCO_GL one set: an invalid value (as a backend whose library is
    missing) made every command a traceback, exit 1."""
    environ = {**os.environ, "MUJOCO_GL": "no-such-backend", "PYTHONPATH": str(ROOT)}
    args = ["--runs", str(tmp_path), "--data", str(tmp_path / "d.npz"), "--out", str(tmp_path / "f.png")]
    proc = subprocess.run(
        [sys.executable, "-m", "pets.visualize", *args], env=environ, capture_output=True, text=True, timeout=120
    )
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "MuJoCo cannot be imported (MUJOCO_GL=no-such-backend: RuntimeError" in lines[0]
    assert "apt-get install -y libegl1" in lines[0]


@pytest.mark.skipif(bool(os.environ.get("DISPLAY")), reason="with a display, glfw can render")
def test_no_usable_gl_is_one_line_exit_2(runs, tmp_path):
    """MUJOCO_GL=glfw without a display: no offscreen context, one line that names the install, exit 2."""
    data, run = runs["halfcheetah"]
    environ = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    environ.update(MUJOCO_GL="glfw", PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    args = ["--runs", str(run), "--data", str(data), "--steps", "0,3", "--out", str(tmp_path / "f.png")]
    proc = subprocess.run(
        [sys.executable, "-m", "pets.visualize", *args], env=environ, capture_output=True, text=True, timeout=120
    )
    lines = [line for line in proc.stderr.splitlines() if line.strip() and "settotalmass" not in line]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "MuJoCo cannot render offscreen (MUJOCO_GL=glfw" in lines[0] and "apt-get install -y libegl1" in lines[0]
    assert not (tmp_path / "f.png").exists()


@pytest.mark.parametrize("name", envs.names())
def test_grid_rows_render_for_every_env(name):
    """The truth of a recorded episode and a 'model' that is the truth plus noise on every predicted entry: the
    same picture at step 0, different ones later, for all 8 envs (cos/sin pairs and quaternions included)."""
    spec = envs.get(name)
    data = collect(spec, "smooth-random", 1, seed=0, max_steps=12)
    truth = data["obs"][0, : data["lengths"][0] + 1]
    wrong = truth.copy()
    predicted = list(spec.layout.predicted_indices)
    wrong[1:, predicted] += np.random.default_rng(0).normal(0.0, 0.3, (len(truth) - 1, len(predicted)))
    steps = [0, len(truth) - 1]
    frames = visualize.render_rows(spec, [truth, wrong], steps, size=SIZE)
    assert frames.shape == (2, 2, SIZE[1], SIZE[0], 3) and min(f.std() for f in frames.reshape(4, -1)) > 5
    assert np.array_equal(frames[0, 0], frames[1, 0])
    assert np.abs(frames[0, 1].astype(int) - frames[1, 1]).mean() > 0.5
    caption = visualize.root_note(spec, "model")
    assert ("Root x" in caption) == bool(spec.layout.invariant)
