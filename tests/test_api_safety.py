"""The Python API keeps the command line's promises (issue 55): ``save`` never writes into a live run or over another
run, ``load`` refuses what ``--resume`` refuses, and bad arguments are one clear error before any work."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import pets
from pets.config import ConfigError
from pets.runs import rundir
from pets.runs.fileio import DirectoryInUse
from tests.threads import one_thread

ROOT = Path(__file__).resolve().parents[1]
TINY = {
    "seed_steps": 60,
    "episode_length": 20,
    "planner.population": 16,
    "planner.horizon": 4,
    "planner.particles": 2,
    "model.hidden_size": 32,
    "model.ensemble_size": 2,
    "model.num_elites": 2,
    "model.max_epochs": 2,
    "value.steps": 20,
}


def _agent(seed: int = 0) -> pets.PETS:
    return pets.PETS("invertedpendulum", model="delta", preset="fast", seed=seed, threads=1, **TINY)


@pytest.fixture(scope="module")
def trained() -> pets.PETS:
    with one_thread():
        return _agent().learn(trials=1)


def _files(path: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(path.iterdir()) if p.is_file() and p.name != ".lock"}


def test_save_into_a_directory_a_command_holds_is_refused_and_writes_nothing(tmp_path, trained):
    run = tmp_path / "live"
    run.mkdir()
    (run / rundir.CONFIG_FILE).write_text("env: live\n")
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pets.runs.fileio import locked\n"
            "with locked(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)",
            str(run),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        before = _files(run)
        with pytest.raises(DirectoryInUse, match="in use by another run.*nothing was saved"):
            trained.save(run)
        assert _files(run) == before
    finally:
        holder.kill()
        holder.wait()


def test_save_over_another_run_is_refused_and_that_run_is_untouched(tmp_path, trained):
    other = tmp_path / "other"
    with one_thread():
        _agent(seed=1).save(other)
    before = _files(other)
    with pytest.raises(ConfigError, match="already holds a run"):
        trained.save(other)
    assert _files(other) == before


def test_save_into_a_folder_of_other_files_is_refused_and_touches_nothing(tmp_path, trained):
    """save wrote a run into any folder without a run's config.yaml or checkpoint.pt: one's own metrics.csv there
    was written over."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "metrics.csv").write_text("my own numbers\n")
    with pytest.raises(ConfigError, match=r"is not empty and holds no run \(metrics.csv\).*save to a new directory$"):
        trained.save(mine)
    assert sorted(p.name for p in mine.iterdir()) == ["metrics.csv"]  # not even a lock file
    assert (mine / "metrics.csv").read_text() == "my own numbers\n"


def test_save_again_where_it_saved_or_was_loaded_from_is_allowed(tmp_path, trained):
    run = trained.save(tmp_path / "mine")
    trained.save(run)  # the same object again: its own run
    again = pets.PETS.load(run)
    again.save(run)
    assert pets.PETS.load(run).trials_done == 1
    with one_thread():
        again.learn(trials=1)
    again.save(run)  # it went on: saved
    with pytest.raises(ConfigError, match="has gone on to 2 trials since this object saved or loaded it"):
        trained.save(run)  # the older object would undo that trial


def test_a_path_that_is_not_one_is_named_in_one_line_and_nothing_is_written(tmp_path, trained, monkeypatch):
    """save(None) was "expected str, bytes or os.PathLike object, not NoneType", and save("") wrote into the working
    directory (or refused it for holding other files)."""
    monkeypatch.chdir(tmp_path)
    for bad, kind in ((None, "NoneType None"), (3, "int 3")):
        for call, name in (
            (trained.save, "PETS.save"),
            (pets.PETS.load, "PETS.load"),
            (pets.load_model, "pets.load_model"),
        ):
            with pytest.raises(
                TypeError, match=f"^{name} takes a run directory \\(str or pathlib.Path\\), got {kind}$"
            ):
                call(bad)
    for call, name in (
        (trained.save, "PETS.save"),
        (pets.PETS.load, "PETS.load"),
        (pets.load_model, "pets.load_model"),
    ):
        with pytest.raises(ConfigError, match=f"^{name} got an empty path; name the run directory$"):
            call("")
    assert list(tmp_path.iterdir()) == []


def test_load_refuses_a_checkpoint_with_nan_in_its_buffer_and_a_missing_checkpoint(tmp_path, trained):
    run = trained.save(tmp_path / "nan")
    state = rundir.load_checkpoint(run)
    state["buffer"]["obs"][3, 0] = np.nan
    rundir.save_checkpoint(run, state)
    with pytest.raises(ConfigError, match="non-finite values"):
        pets.PETS.load(run)
    (run / rundir.CHECKPOINT_FILE).unlink()
    with pytest.raises(ConfigError, match="checkpoint.pt is missing although the run records 1 completed"):
        pets.PETS.load(run)


def test_predict_and_rollout_refuse_what_is_not_an_array_of_numbers_or_has_no_steps(trained):
    model = trained.model
    with pytest.raises(ValueError, match="must be an array of numbers"):
        model.predict("obs", "act")
    with pytest.raises(ValueError, match="observations must be an array of numbers"):
        model.predict("obs", np.zeros(1))
    with pytest.raises(ValueError, match="no steps: a rollout needs a horizon H >= 1"):
        model.rollout(np.zeros((8, 4)), np.zeros((8, 0, 1)))
    assert model.predict([0.0, 0.0, 0.0, 0.0], [0.0]).shape == (4,)
    assert isinstance(model.rollout(torch.zeros(2, 4), torch.zeros(2, 3, 1)), torch.Tensor)


def test_numpy_integers_are_accepted_as_config_values():
    agent = pets.PETS("invertedpendulum", preset="fast", **{"planner.population": np.int64(50)}, seed=np.int64(2))
    assert agent.config.planner.population == 50 and agent.config.seed == 2
    assert type(agent.config.planner.population) is int


def test_a_callback_that_is_not_callable_fails_before_any_work():
    agent = pets.PETS("invertedpendulum", preset="fast", **TINY)
    start = time.perf_counter()
    with pytest.raises(ValueError, match="callback must be a function"):
        agent.learn(trials=1, callback=5)
    assert time.perf_counter() - start < 1 and agent.trials_done == 0 and len(agent._run.buffer) == 0


def _learned(agent: pets.PETS) -> list[dict]:
    return [{k: v for k, v in row.items() if k not in rundir.TIMING_COLUMNS} for row in agent.history]


def test_a_trial_interrupted_by_ctrl_c_is_undone_and_learning_again_replays_it(trained):
    """A KeyboardInterrupt in the middle of learn left the trial's data in the buffer and its training half done,
    with trials_done as before: learning again planned with an untrained model or added the episode twice."""
    agent = _agent()
    train, calls = agent._run.trainer.train, []

    def interrupted(*args, **kwargs):  # the seed data's training passes, trial 0's is interrupted
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return train(*args, **kwargs)

    agent._run.trainer.train = interrupted
    with one_thread(), pytest.raises(KeyboardInterrupt):
        agent.learn(trials=1)
    assert agent.trials_done == 0 and len(agent._run.buffer) == 0 and agent._run.env_steps == 0
    agent._run.trainer.train = train
    with one_thread():
        agent.learn(trials=1)
    assert _learned(agent) == _learned(trained)
    for p, q in zip(agent.model.state_dict().values(), trained.model.state_dict().values()):
        assert torch.equal(p, q)


def test_acting_between_learn_calls_leaves_what_they_learn_as_it_was():
    """act drew from the planner's generator that learning uses: a look at the agent between two learn calls
    changed the second call's metrics."""
    with one_thread():
        looked = _agent().learn(trials=1)
        for _ in range(2):
            looked.act(np.zeros(4))
        looked.learn(trials=1)
        assert _learned(looked) == _learned(_agent().learn(trials=2))


def test_act_refuses_an_observation_of_another_shape_or_not_of_numbers(trained):
    """A wrong width was refused deep in the planner ("obs0 must have shape"), and not at all at a step between
    replans; a batch the same; None was "obs holds nan or inf"; complex numbers lost their imaginary part."""
    for bad, fragment in (
        (np.zeros(3), r"obs must have shape \(4,\), the env's observation, got \(3,\)$"),
        (np.zeros((2, 4)), r"got \(2, 4\) \(act takes one observation, not a batch\)"),
        (None, "obs must be an array of numbers, got NoneType"),
        (np.zeros(4, dtype=complex), "obs must be an array of numbers, got ndarray"),
        ([[0.0], [0.0, 1.0]], "obs must be an array of numbers, got list"),
    ):
        with pytest.raises(ValueError, match=fragment):
            trained.act(bad)
    with one_thread():
        for good in ([0.0] * 4, torch.zeros(4, requires_grad=True), np.zeros(4, dtype=np.int64)):
            assert trained.act(good).shape == (1,)


def test_predict_and_rollout_name_the_shapes_given(trained):
    """predict named its internal (3, 1, 1) for actions (3, 1); rollout of a single number raised IndexError."""
    model = trained.model
    with pytest.raises(
        ValueError, match=r"observations \(\.\.\., 4\) and actions \(\.\.\., 1\), got \(3, 5\) and \(3, 1\)"
    ):
        model.predict(np.zeros((3, 5)), np.zeros((3, 1)))
    for obs, act in ((np.zeros(4), 5.0), (0.0, np.zeros((2, 1)))):
        with pytest.raises(ValueError, match=r"expected observations \(\.\.\., 4\) and actions \(\.\.\., H, 1\)"):
            model.rollout(obs, act)
