"""What a run leaves to look at besides metrics.csv: episode videos (read back with imageio) and TensorBoard
event files (read back with TensorBoard's own event reader), also across a resume."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from pets.runs import rundir
from pets.runs.tblog import TRIAL_TAGS
from tests.test_cli import ROOT, TINY, cli, error_lines
from tests.tiny import replacing


def rows(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of the run directory's event files: tag -> [(step, value)] (TensorBoard's purge applied)."""
    acc = EventAccumulator(str(run_dir))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def test_one_trial_with_video_1_writes_an_mp4_of_the_episode(tmp_path):
    out, plain = tmp_path / "run", tmp_path / "plain"
    cli("--env", "halfcheetah", "--trials", 1, "--video", 1, "--out", out, *TINY)
    video = out / "videos" / "trial-0000.mp4"
    frames = iio.imread(video)  # every frame, decoded by imageio (its ffmpeg plugin)
    length = int(rows(out)[0]["episode_length"])
    assert length == 30 and frames.shape == (length, 240, 320, 3)
    assert frames.std() > 5 and abs(frames[0].astype(int) - frames[-1]).mean() > 1  # not blank; it moves
    assert "video_every: 1" in (out / "config.yaml").read_text()
    cli("--env", "halfcheetah", "--trials", 1, "--out", plain, *TINY)  # filming changes nothing in the run
    timing = rundir.TIMING_COLUMNS
    assert [{k: v for k, v in r.items() if k not in timing} for r in rows(out)] == [
        {k: v for k, v in r.items() if k not in timing} for r in rows(plain)
    ]
    assert not (plain / "videos").exists()


def test_video_every_2_films_trials_0_and_2_only(tmp_path):
    out = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 3, "video_every=2", "--out", out, *TINY)
    assert sorted(p.name for p in (out / "videos").iterdir()) == ["trial-0000.mp4", "trial-0002.mp4"]
    for trial in (0, 2):
        frames = iio.imread(out / "videos" / f"trial-{trial:04d}.mp4")
        assert len(frames) == int(rows(out)[trial]["episode_length"])


def test_event_files_hold_every_trials_scalars_and_a_resume_repeats_none(tmp_path):
    out = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--out", out, *TINY)
    # An interrupted trial 1 that wrote its scalars but was killed before its checkpoint:
    from torch.utils.tensorboard import SummaryWriter

    stale_step = int(rows(out)[0]["env_steps"]) + 5
    with SummaryWriter(str(out)) as writer:
        writer.add_scalar("episode/reward", 999.0, stale_step)
    cli("--resume", out, "--trials", 3, "--quiet")
    metrics, logged = rows(out), scalars(out)
    assert set(logged) == set(TRIAL_TAGS.values())
    for column, tag in TRIAL_TAGS.items():
        expected = [(int(r["env_steps"]), float(r[column])) for r in metrics]
        assert [step for step, _ in logged[tag]] == [step for step, _ in expected], tag
        assert all(math.isclose(v, e, rel_tol=1e-6, abs_tol=1e-6) for (_, v), (_, e) in zip(logged[tag], expected))
    assert 999.0 not in [v for _, v in logged["episode/reward"]]


def test_without_the_tensorboard_package_a_run_says_so_once_and_keeps_the_csv(tmp_path):
    out = tmp_path / "run"
    argv = [str(a) for a in ("--env", "invertedpendulum", "--trials", 2, "--out", out, *TINY)]
    code = (  # the package made unimportable, as on a machine without it
        f"import sys; sys.modules['tensorboard'] = None; import run_pets; sys.exit(run_pets.main({argv!r}))"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("tensorboard is not installed") == 1
    assert len(rows(out)) == 2 and not list(out.glob("events.out.tfevents.*"))


def test_tensorboard_false_writes_no_events(tmp_path):
    out = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "tensorboard=false", "--out", out, *TINY)
    assert not list(out.glob("events.out.tfevents.*")) and (out / "metrics.csv").is_file()


@pytest.mark.parametrize("value", ["-1", "x"])
def test_bad_video_every_is_one_line_exit_2(tmp_path, value):
    proc = cli("--env", "invertedpendulum", "--video", value, "--out", tmp_path / "r", *TINY, check=False)
    assert proc.returncode == 2 and len(error_lines(proc.stderr)) == 1
    assert not (tmp_path / "r" / "config.yaml").exists()


@pytest.fixture(scope="module")
def offline(tmp_path_factory):
    """A small HalfCheetah data set and a tiny model trained on it offline (pets.train)."""
    import envs
    from pets.data.collect import collect
    from pets.data.datasets import save_dataset
    from pets.learning.offline import train_offline
    from tests.tiny import TINY_MODEL

    work = tmp_path_factory.mktemp("offline")
    data = save_dataset(
        work / "hc-test.npz", collect(envs.get("halfcheetah"), "smooth-random", 2, seed=0, max_steps=20)
    )
    overrides = dict(item.split("=") for item in TINY_MODEL) | {"threads": "1"}
    return data, train_offline(data, "delta", work / "run", overrides, preset="fast", seed=0)


def test_offline_training_writes_its_result_as_events(offline):
    _, run = offline
    logged, row = scalars(run), rows(run)[0]
    for column in ("model_train_loss", "model_val_loss", "model_epochs", "wall_time_s"):
        [(step, value)] = logged[TRIAL_TAGS[column]]
        assert step == 0 and math.isclose(value, float(row[column]), rel_tol=1e-6)
    assert "episode/reward" not in logged  # no episode in an offline run


def test_evaluate_tensorboard_writes_per_horizon_errors_once(offline, tmp_path):
    from pets import evaluate

    data, run = offline
    for _ in range(2):  # evaluated twice: the second replaces the first
        args = ["--run", str(run), "--data", str(data), "--horizons", "1,5", "--starts", "8", "--threads", "1"]
        assert evaluate.main([*args, "--json", str(tmp_path / "e.json"), "--tensorboard"]) == 0
    result = json.loads((tmp_path / "e.json").read_text())
    logged = scalars(run / "eval" / "hc-test")
    for metric in ("mean_step_error", "final_step_error", "rotation_error", "standardized_error"):
        got = logged[f"eval/{metric}"]
        assert [s for s, _ in got] == [1, 5]
        assert all(math.isclose(v, result["horizons"][str(s)][metric], rel_tol=1e-6) for s, v in got)


def test_openloop_video_has_a_frame_per_executed_step(offline, tmp_path):
    from pets import openloop
    from tests.tiny import TINY_PLANNER

    _, run = offline
    out = tmp_path / "videos"
    tiny = [t for t in TINY_PLANNER if not t.startswith("planner.horizon")]
    args = ["--run", str(run), "--steps", "6", "--episodes", "2", "--threads", "1", "--quiet", "--video", str(out)]
    assert openloop.main([*args, "--json", str(tmp_path / "o.json"), *tiny]) == 0
    result = json.loads((tmp_path / "o.json").read_text())
    assert result["videos"] == [str(out / "episode-0.mp4"), str(out / "episode-1.mp4")]
    for path, length in zip(result["videos"], result["lengths"]):
        frames = iio.imread(path)
        assert length == 6 and frames.shape == (6, 240, 320, 3) and frames.std() > 5


def test_metrics_split_each_trials_cpu_into_planning_training_and_the_value(tmp_path):
    """plan_cpu_s, train_cpu_s and value_cpu_s: process CPU seconds of the trial's planning, model training and
    terminal-value fit; together never more than the trial's share of the cumulative cpu_time_s; the value's is 0
    without a value, positive with one; trial 0's training includes the seed data's."""
    with_value, without = tmp_path / "value", tmp_path / "plain"
    cli(
        "--env",
        "invertedpendulum",
        "--trials",
        2,
        "value.enabled=true",
        "--out",
        with_value,
        *replacing(TINY, "value.steps=50"),
    )
    cli("--env", "invertedpendulum", "--trials", 2, "value.enabled=false", "--out", without, *TINY)
    for run_dir, valued in ((with_value, True), (without, False)):
        before = 0.0
        for r in rows(run_dir):
            plan, train, value = (float(r[k]) for k in ("plan_cpu_s", "train_cpu_s", "value_cpu_s"))
            spent = float(r["cpu_time_s"]) - before
            before = float(r["cpu_time_s"])
            assert plan > 0 and train > 0 and (value > 0) == valued, (run_dir.name, r)
            assert plan + train + value <= spent + 1e-3, (run_dir.name, r)
