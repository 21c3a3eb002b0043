"""The one-line estimate of a long run (pets.planning.cost) and where run_pets.py prints it (issue 13 item 4)."""

import pytest

from pets.config import make_config
from pets.planning import cost
from tests.test_cli import TINY


def test_a_long_run_gets_one_line_naming_faster_options():
    cfg = make_config("halfcheetah", "delta", "research", {"planner.precision": "fp32"})
    est = cost.CostEstimate(cfg, steps_per_trial=1000, trials_left=300)
    lines = [est.step(i, 2.0 + 3.5 * max(0, i - cost.WARMUP_STEPS)) for i in range(1, 40)]
    (line,) = [x for x in lines if x]  # once, after the warm-up and the measured steps
    assert lines.index(line) == cost.WARMUP_STEPS + cost.MEASURED_STEPS - 1
    # 3.5 s per step x 1000 steps x 300 trials = 291.7 h
    assert line.startswith("estimated time: about 12 d 3 h of planning for the 300 trials left (3.50 s per planning")
    assert "--preset fast" in line and "planner.name=icem" in line and "planner.compile=true" in line
    assert "\n" not in line


def test_a_short_run_gets_no_line_and_used_options_are_not_offered():
    cfg = make_config("halfcheetah", "delta", "fast", {"planner.name": "icem", "planner.compile": "true"})
    assert cost.long_run_line(cfg, 0.1, 1000, 10) is None  # 17 min
    line = cost.long_run_line(cfg, 0.1, 1000, 300)  # 8 h 20 min
    assert line is not None and "8 h 20 min" in line
    assert "--preset fast" not in line and "icem" not in line and "compile" not in line


def test_a_run_with_an_env_step_budget_is_estimated_for_the_budget_not_its_trials():
    """The locomotion preset's trials are a mere upper bound (100,000); its budget of env steps ends the run."""
    cfg = make_config("halfcheetah", "delta", "locomotion")
    line = cost.long_run_line(cfg, 0.12, 1000, 100_000, steps_left=99_000)  # 0.12 s x 99,000 steps = 3 h 18 min
    assert line is not None and "about 3 h 18 min of planning for the 99000 env steps left of the budget" in line
    assert cost.long_run_line(cfg, 0.1, 1000, 100_000, steps_left=99_000) is None  # 2 h 45 min: no line


def test_feedback_candidates_are_not_offered_settings_they_cannot_use():
    """IDP's fast preset plans feedback gains with CEM over a 60-step closed loop: iCEM does not search gains and
    the fast preset is what it already is, so neither is offered."""
    cfg = make_config("inverteddoublependulum", "gem", "fast")
    line = cost.long_run_line(cfg, 0.5, 1000, 60)
    assert line is not None and "icem" not in line and "--preset fast" not in line and "compile=true" in line


@pytest.mark.parametrize("seconds, text", [(59, "1 min"), (7500, "2 h 05 min"), (86400 * 3 + 7200, "3 d 2 h")])
def test_format_duration(seconds, text):
    assert cost.format_duration(seconds) == text


def test_run_pets_prints_the_line_once_per_session(tmp_path, monkeypatch, capsys):
    """With the threshold at 0 h every run is long: one line on stderr, after the first planning steps."""
    import run_pets

    monkeypatch.setattr(cost, "LONG_RUN_HOURS", 0.0)
    monkeypatch.setattr(cost, "WARMUP_STEPS", 1)
    monkeypatch.setattr(cost, "MEASURED_STEPS", 1)
    out = tmp_path / "run"
    assert run_pets.main(["--env", "invertedpendulum", "--trials", "2", "--out", str(out), *TINY]) == 0
    err = capsys.readouterr().err
    assert err.count("estimated time: about") == 1, err
    assert "for the 2 trials left" in err


def test_the_compile_line_names_each_compiled_path():
    cfg = make_config("reacher", "gem", "fast", {"model.compile": "true", "planner.compile": "false"})
    line = cost.compile_line(cfg)
    assert line is not None and "training step (6-15 CPU-s" in line and "rollout step" not in line
    cfg.planner.compile = True
    assert "rollout step" in cost.compile_line(cfg)
    assert cost.compile_line(make_config("reacher", "gem", "research")) is None  # eager: no line


def test_run_pets_states_the_compile_cost_at_the_start(tmp_path, monkeypatch, capsys):
    """model.compile on (here with torch.compile replaced by the eager function: no inductor build in the tests):
    one line on stderr at the start of the run, none on a resume that has nothing left to do."""
    import run_pets
    from pets.learning import compiled

    monkeypatch.setattr(compiled.torch, "compile", lambda fn, **kwargs: fn)
    out = tmp_path / "run"
    args = ["--env", "invertedpendulum", "--trials", "1", "--out", str(out), *TINY, "model.compile=true"]
    assert run_pets.main(args) == 0
    assert capsys.readouterr().err.count("compiling once per run: the first training compiles") == 1
    assert run_pets.main(["--resume", str(out)]) == 0
    assert "compiling once per run" not in capsys.readouterr().err
