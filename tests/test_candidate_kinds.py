"""A candidate kind of one's own (``pets.planning.particles.register_candidates``), registered by a module of the
config key ``imports``: a ``planner.candidates`` value of the config with its settings section ``planner.<kind>.*``,
rolled out by the evaluator and planned with by ``run_pets.py``; a taken name or an unknown kind: one line."""

import sys

import pytest
import torch

#: A kind of one's own, outside the package: action sequences whose every action is held for ``repeat`` steps
#: (its own setting, ``planner.held.repeat``).
HELD = """
from dataclasses import dataclass

from pets.planning.particles import OpenLoop, register_candidates


@dataclass
class HeldSettings:
    repeat: int = 2


class Held(OpenLoop):
    section = HeldSettings

    def __init__(self, law=None, repeat=1):
        super().__init__(law)
        self.repeat = repeat

    @classmethod
    def build(cls, planner, spec, device):
        return cls(repeat=planner.held.repeat)

    @staticmethod
    def check_config(planner):
        if planner.held.repeat < 1:
            raise ValueError(f"planner.held.repeat must be >= 1, got {planner.held.repeat}")

    def action(self, t, per_row, obs):
        return per_row[t - t % self.repeat]


register_candidates("held", Held)
"""


@pytest.fixture
def held(tmp_path, monkeypatch):
    """The module ``my_kind`` (:data:`HELD`) in a folder on the path (removed again after the test)."""
    (tmp_path / "my_kind.py").write_text(HELD)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [str(tmp_path), *sys.path])
    return tmp_path


def test_a_kind_of_imports_is_a_config_choice_with_its_own_section(held) -> None:
    from pets.config import ConfigError, all_keys, make_config
    from pets.planning.particles import CANDIDATE_TABLE
    from pets.planning.propagation import CANDIDATES

    assert tuple(CANDIDATES) == tuple(CANDIDATE_TABLE) == ("open_loop", "feedback")
    assert "planner.feedback.gain_bound" in all_keys() and "planner.held.repeat" not in all_keys()
    with pytest.raises(ConfigError, match=r"^planner\.candidates must be one of open_loop, feedback, got 'held'$"):
        make_config("invertedpendulum", preset="fast", overrides={"planner.candidates": "held"})
    overrides = {"imports": ["my_kind"], "planner.candidates": "held", "planner.held.repeat": "3"}
    cfg = make_config("invertedpendulum", preset="fast", overrides=overrides)
    assert cfg.planner.candidates == "held" and cfg.planner.held.repeat == 3 and "held" in CANDIDATES
    assert "planner.held.repeat" in all_keys() and cfg.planner.feedback.gain_bound == 10.0  # feedback's still there
    with pytest.raises(ConfigError, match=r"^planner\.held\.repeat must be >= 1, got 0$"):  # the kind's own check
        make_config("invertedpendulum", preset="fast", overrides={**overrides, "planner.held.repeat": "0"})
    with pytest.raises(ConfigError, match=r"^planner\.candidates must be one of open_loop, feedback, held, got 'x'$"):
        make_config("invertedpendulum", preset="fast", overrides={"planner.candidates": "x"})


def test_the_evaluator_rolls_out_the_registered_kind(held) -> None:
    """The builder makes the kind of the config (its ``build``, with its setting) for the agent's evaluator; an
    evaluator of the kind returns, with repeat 2, what open-loop candidates with every other action repeated return,
    with repeat 1 what the candidates themselves return."""
    import envs
    from pets.builder import make_agent
    from pets.config import make_config
    from pets.models import make_model
    from pets.planning.propagation import TrajectoryEvaluator

    spec = envs.get("invertedpendulum")
    overrides = {"imports": ["my_kind"], "planner.candidates": "held", "planner.held.repeat": "2"}
    cfg = make_config("invertedpendulum", preset="fast", overrides={**overrides, "device": "cpu"})
    torch.manual_seed(0)
    model = make_model(cfg, spec, torch.device("cpu"))
    agent = make_agent(cfg, spec, model, torch.device("cpu"), torch.Generator().manual_seed(0))
    held_kind = agent.evaluator._candidates
    assert type(held_kind).__name__ == "Held" and held_kind.repeat == 2 and agent.evaluator.feedback is None

    def reward(obs, act, nxt):  # depends on the actions and the states, so that every action counts
        return nxt.sum(-1) - act.square().sum(-1)

    held_ev, plain = (TrajectoryEvaluator(model, reward, None, particles=2, candidates=c) for c in (held_kind, None))
    obs0 = torch.zeros(spec.obs_dim)
    actions = torch.rand(6, 5, spec.act_dim, generator=torch.Generator().manual_seed(1)) * 2 - 1
    repeated = actions[:, [0, 0, 2, 2, 4]]
    returns = [
        ev(obs0, a, torch.Generator().manual_seed(0))
        for ev, a in ((held_ev, actions), (plain, repeated), (plain, actions))
    ]
    assert torch.equal(returns[0], returns[1]) and not torch.equal(returns[0], returns[2])
    held_kind.repeat = 1
    assert torch.equal(held_ev(obs0, actions, torch.Generator().manual_seed(0)), returns[2])
    with pytest.raises(ValueError, match="candidates must be a candidate kind"):
        TrajectoryEvaluator(model, reward, None, candidates="held")  # type: ignore[arg-type]


def test_run_pets_plans_with_a_kind_of_imports(held, capsys) -> None:
    import run_pets
    from tests.test_cli import TINY

    out = held / "run"
    args = ["--env", "invertedpendulum", "--trials", "1", "--out", str(out), *TINY, "value.enabled=false"]
    assert run_pets.main([*args, "imports=[my_kind]", "planner.candidates=held", "planner.held.repeat=2"]) == 0
    assert (out / "metrics.csv").read_text().count("\n") == 2  # the header and the one trial
    written = (out / "config.yaml").read_text()
    assert "candidates: held" in written and "held:\n    repeat: 2" in written
    from pets.config import ConfigError, load_run_config
    from pets.planning.particles import CANDIDATE_TABLE

    assert load_run_config(out).planner.held.repeat == 2  # its imports first, then its section
    capsys.readouterr()
    other = ["--env", "invertedpendulum", "--trials", "1", "--out", str(held / "other"), *TINY]
    with pytest.raises(SystemExit) as exit_:
        run_pets.main([*other, "imports=[my_kind]", "planner.candidates=nope"])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    expected = "run_pets.py: error: planner.candidates must be one of open_loop, feedback, held, got 'nope'"
    assert exit_.value.code == 2 and lines == [expected], lines
    del CANDIDATE_TABLE["held"]  # as in a new process that has not registered it (the table is restored after)
    with pytest.raises(ConfigError, match="its candidate kind 'held' is not a kind here .* register_candidates") as err:
        load_run_config(out)
    assert "\n" not in str(err.value)


def test_a_taken_name_or_a_class_that_is_not_a_kind_is_refused() -> None:
    from pets.planning.particles import CANDIDATE_TABLE, FeedbackGains, OpenLoop, register_candidates

    class Mine(OpenLoop):
        pass

    with pytest.raises(ValueError, match=r"^candidate kind 'feedback' is taken \(FeedbackGains\); give yours another"):
        register_candidates("feedback", Mine)
    with pytest.raises(ValueError, match=r"^candidate kind 'open_loop' is taken \(OpenLoop\)"):
        register_candidates("open_loop", Mine)
    with pytest.raises(ValueError, match=r"must be a subclass of particles\.OpenLoop, got <class 'int'>"):
        register_candidates("mine", int)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"must be an identifier \(a config key\), got 'my kind'"):
        register_candidates("my kind", Mine)
    Mine.section = dict  # type: ignore[assignment]
    with pytest.raises(ValueError, match=r"its section must be a dataclass or None"):
        register_candidates("mine", Mine)
    assert register_candidates("feedback", FeedbackGains) is FeedbackGains  # the same class again: a re-import
    Mine.section = None
    again = type("Mine", (OpenLoop,), {"__module__": Mine.__module__, "__qualname__": Mine.__qualname__})
    assert register_candidates("mine", Mine) is Mine and register_candidates("mine", again) is again  # re-imported
    other = type("Mine", (OpenLoop,), {"__module__": "my_other_kinds", "__qualname__": Mine.__qualname__})
    with pytest.raises(ValueError, match=r"^candidate kind 'mine' is taken \(.*Mine\)"):  # another module's Mine
        register_candidates("mine", other)
    assert tuple(CANDIDATE_TABLE) == ("open_loop", "feedback", "mine")


@pytest.mark.parametrize("name", ["horizon", "mppi"])
def test_a_section_on_a_shared_setting_or_another_section_is_one_line(name) -> None:
    """A kind whose section would be ``planner.horizon`` (a shared setting) or ``planner.mppi.*`` (MPPI's section):
    the config refuses it in one line, naming the key (the table is restored after the test)."""
    from dataclasses import make_dataclass

    from pets.config import ConfigError, make_config
    from pets.planning.particles import OpenLoop, register_candidates

    register_candidates(name, type("Mine", (OpenLoop,), {"section": make_dataclass("S", [("k", int, 1)])}))
    with pytest.raises(ConfigError, match=rf"^planner\.{name} is the section of a planner or kind and another"):
        make_config("invertedpendulum", preset="fast")
