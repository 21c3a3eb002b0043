"""Linear-feedback candidates (planner.candidates=feedback): the law, closed-loop rollouts in the model and in
MuJoCo, the agent, the config and a run that resumes with its feature scale."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import envs
from dynamics.model import DynamicsModel
from pets import builder, oracle
from pets.agent import MPCAgent
from pets.config import ConfigError, make_config, parse_overrides
from pets.models import make_model
from pets.planning.feedback import LinearFeedback
from pets.planning.planners import CEMPlanner
from pets.planning.propagation import PROPAGATIONS, TrajectoryEvaluator
from tests.test_propagation import ACT_DIM, OBS_DIM, FakeEnsemble, make_head, reward_fn
from tests.tiny import TINY_MODEL, TINY_PLANNER

ROOT = Path(__file__).resolve().parents[1]
LOW, HIGH = np.array([-1.0, -0.5]), np.array([2.0, 0.5])


def law(obs: np.ndarray, gains: np.ndarray, features, scale, bias: bool) -> np.ndarray:
    """The documented law in numpy: clip(mid + half * (z @ K)), z = obs[features] / scale (+ 1)."""
    z = obs[features] / scale
    if bias:
        z = np.append(z, 1.0)
    mid, half = (LOW + HIGH) / 2, (HIGH - LOW) / 2
    return np.clip(mid + half * (z @ gains), LOW, HIGH)


@pytest.mark.parametrize("bias", [False, True])
def test_the_law_is_the_documented_formula_and_stays_in_the_box(bias: bool) -> None:
    features, scale = [2, 0], [0.5, 2.0]
    fb = LinearFeedback(OBS_DIM, LOW, HIGH, horizon=3, features=features, scale=scale, bias=bias)
    assert fb.shape == (2 + bias, ACT_DIM)
    rng = np.random.default_rng(0)
    obs, gains = rng.normal(size=(64, OBS_DIM)), rng.normal(size=(64, *fb.shape))
    got = fb.actions(torch.tensor(gains, dtype=torch.float32), torch.tensor(obs, dtype=torch.float32)).numpy()
    want = np.stack([law(o, k, features, np.array(scale), bias) for o, k in zip(obs, gains)])
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert (got >= LOW).all() and (got <= HIGH).all() and (got == HIGH).any() and (got == LOW).any()


def test_the_fitted_scale_is_the_features_std_and_a_fixed_one_is_kept() -> None:
    obs = torch.randn(500, OBS_DIM, generator=torch.Generator().manual_seed(0)) * torch.tensor([3.0, 0.0, 0.2])
    fb = LinearFeedback(OBS_DIM, LOW, HIGH, horizon=2)
    fb.fit_scale(obs)
    want = np.maximum(np.std(obs.numpy(), axis=0, ddof=1), 1e-3)  # a constant feature is floored, not divided by 0
    np.testing.assert_allclose(fb.scale.numpy(), want, rtol=1e-5)
    fixed = LinearFeedback(OBS_DIM, LOW, HIGH, horizon=2, features=[1], scale=[0.7])
    fixed.fit_scale(obs)
    assert fixed.scale.tolist() == pytest.approx([0.7])
    restored = LinearFeedback(OBS_DIM, LOW, HIGH, horizon=2)
    restored.load_state_dict(fb.state_dict())
    assert torch.equal(restored.scale, fb.scale)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"features": [0, 3]}, "distinct observation indices in [0, 3)"),
        ({"features": [1, 1]}, "distinct"),
        ({"features": []}, "distinct"),
        ({"features": [0, 1], "scale": [1.0]}, "one positive value per feature (2)"),
        ({"scale": [1.0, 0.0, 1.0]}, "one positive value per feature"),
        ({"horizon": 0}, "horizon must be a positive int"),
    ],
)
def test_bad_arguments_are_clear_errors(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
        LinearFeedback(OBS_DIM, LOW, HIGH, **{"horizon": 2, **kwargs})


def _closed_loop_return(obs0, gains, fb, a_mat, b_mat, c) -> float:
    """Ground truth: a Python loop of obs' = obs + obs A + act B + c with the numpy law, summing reward_fn."""
    obs, total = obs0.double().numpy(), 0.0
    for _ in range(fb.horizon):
        act = law(obs, gains.numpy(), fb.features.tolist(), fb.scale.double().numpy(), fb.bias)
        nxt = obs + obs @ a_mat.double().numpy() + act @ b_mat.double().numpy() + c.double().numpy()
        total += float(reward_fn(torch.tensor(obs), torch.tensor(act), torch.tensor(nxt)))
        obs = nxt
    return total


@pytest.mark.parametrize("prop", PROPAGATIONS)
def test_closed_loop_returns_in_the_model_match_a_python_loop(prop: str) -> None:
    """Noise-free identical members: every propagation mode returns the closed-loop sum of rewards, each particle's
    action computed from its own state (so the returns differ from any open-loop sequence's)."""
    g = torch.Generator().manual_seed(0)
    a_mat = 0.2 * torch.randn(OBS_DIM, OBS_DIM, generator=g)
    b_mat = 0.5 * torch.randn(ACT_DIM, OBS_DIM, generator=g)
    c = torch.tensor([0.05, -0.02, 0.01])
    fb = LinearFeedback(OBS_DIM, LOW, HIGH, horizon=7, bias=True)
    fb.scale = torch.tensor([0.5, 1.0, 2.0])
    model = DynamicsModel(make_head(), FakeEnsemble(c.expand(5, OBS_DIM), a_mat=a_mat, b_mat=b_mat))
    ev = TrajectoryEvaluator(model, reward_fn, None, particles=3, propagation=prop, feedback=fb)
    obs0 = torch.tensor([0.3, -0.2, 0.1])
    gains = torch.randn(6, *fb.shape, generator=g)
    got = ev(obs0, gains, g)
    want = torch.tensor([_closed_loop_return(obs0, k, fb, a_mat, b_mat, c) for k in gains], dtype=torch.double)
    torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-5)
    obs, rew = ev.rollout(obs0, gains, g)
    assert obs.shape == (6, 3, fb.horizon + 1, OBS_DIM) and rew.shape == (6, 3, fb.horizon)
    torch.testing.assert_close(rew.sum(-1).mean(-1), got)


@pytest.mark.parametrize("prop", ["ts1", "tsinf"])
def test_zero_gains_roll_out_exactly_as_the_constant_open_loop_sequence(prop: str) -> None:
    """With K = 0 the law is the box centre at every state: the sampled returns (same generator state) equal those
    of the open-loop sequence of centre actions, bit for bit."""
    fb = LinearFeedback(OBS_DIM, LOW, HIGH, horizon=5)
    ens = FakeEnsemble(torch.randn(4, OBS_DIM, generator=torch.Generator().manual_seed(1)), logvar=-2.0)
    model = DynamicsModel(make_head(), ens)
    closed = TrajectoryEvaluator(model, reward_fn, None, particles=4, propagation=prop, feedback=fb)
    open_loop = TrajectoryEvaluator(model, reward_fn, None, particles=4, propagation=prop)
    obs0 = torch.tensor([0.1, 0.2, -0.3])
    centre = torch.tensor((LOW + HIGH) / 2, dtype=torch.float32).expand(3, 5, ACT_DIM)
    got = closed(obs0, torch.zeros(3, *fb.shape), torch.Generator().manual_seed(7))
    want = open_loop(obs0, centre, torch.Generator().manual_seed(7))
    assert torch.equal(got, want)


def test_gains_of_the_wrong_shape_are_a_clear_error() -> None:
    fb = LinearFeedback(OBS_DIM, LOW, HIGH, horizon=5, features=[0])
    model = DynamicsModel(make_head(), FakeEnsemble(torch.zeros(2, OBS_DIM)))
    ev = TrajectoryEvaluator(model, reward_fn, None, particles=2, feedback=fb)
    with pytest.raises(ValueError, match=r"gains of shape \(N, 1, 2\), got \(4, 5, 2\)"):
        ev(torch.zeros(OBS_DIM), torch.zeros(4, 5, ACT_DIM))


def test_the_agent_plans_gains_every_step_and_acts_by_the_law() -> None:
    fb = LinearFeedback(OBS_DIM, LOW, HIGH, horizon=4, features=[0, 1])
    model = DynamicsModel(make_head(), FakeEnsemble(torch.zeros(2, OBS_DIM), b_mat=torch.ones(ACT_DIM, OBS_DIM)))
    ev = TrajectoryEvaluator(model, reward_fn, None, particles=2, feedback=fb)
    planner = CEMPlanner(-np.ones(2), np.ones(2), horizon=fb.shape[0], population=20, iterations=2, init_std=0.3)
    calls, plans = [], []
    plan = planner.plan

    def recording_plan(objective, init, generator):
        calls.append(None if init is None else init.clone())
        plans.append(plan(objective, init, generator))
        return plans[-1]

    planner.plan = recording_plan

    def agent_of(replan_every: int) -> MPCAgent:
        kwargs = dict(action_low=LOW, action_high=HIGH, device=torch.device("cpu"), feedback=fb)
        return MPCAgent(planner, ev, replan_every=replan_every, generator=torch.Generator().manual_seed(0), **kwargs)

    agent = agent_of(1)
    obs = np.array([0.4, -0.3, 0.2])
    for _ in range(3):
        action = agent.act(obs)
        want = law(obs, agent._plan.numpy().astype(np.float64), [0, 1], np.ones(2), False)
        np.testing.assert_allclose(action, want, rtol=1e-6)
    assert len(calls) == 3 and calls[0] is None  # one plan per step, the first from zero gains
    assert torch.equal(calls[1], plans[0]) and torch.equal(calls[2], plans[1])  # then from the last gains
    agent.reset()
    agent.act(obs)
    assert calls[3] is None  # a new episode starts from zero gains
    with pytest.raises(ValueError, match="replan_every must be 1"):
        agent_of(2)


def test_the_simulator_scores_gains_by_the_law_in_closed_loop_through_mujoco() -> None:
    spec = envs.get("inverteddoublependulum")
    env = spec.make()
    obs, _ = env.reset(seed=2)
    fb = LinearFeedback(
        spec.obs_dim,
        spec.action_low,
        spec.action_high,
        horizon=25,
        features=[0, 1, 2, 5, 6, 7],
        scale=[0.5, 0.2, 0.2, 1.0, 2.0, 2.0],
    )
    gains = torch.randn(3, *fb.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    got = oracle.SimulatorEvaluator(env, spec.make, fb)(torch.as_tensor(obs), gains)
    for k, ret in zip(gains, got.tolist()):  # the real env from the same state, stepped with the numpy law
        real = spec.make()
        real.reset(seed=0)
        real.unwrapped.set_state(env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy())
        o, total = obs, 0.0
        for _ in range(fb.horizon):
            z = o[[0, 1, 2, 5, 6, 7]] / np.array([0.5, 0.2, 0.2, 1.0, 2.0, 2.0])
            o, r, terminated, _, _ = real.unwrapped.step(np.clip(z @ k.numpy(), -1, 1))
            total += r
            if terminated:
                break
        assert ret == pytest.approx(total, rel=1e-6)


def test_config_checks_and_list_overrides() -> None:
    cfg = make_config(
        "inverteddoublependulum",
        "gem",
        "fast",
        parse_overrides(
            ["planner.candidates=feedback", "planner.feedback.features=[0, 1, 5]", "planner.feedback.scale=[1,2,3]"]
        ),
    )
    assert list(cfg.planner.feedback.features) == [0, 1, 5] and list(cfg.planner.feedback.scale) == [1.0, 2.0, 3.0]
    spec = envs.get("inverteddoublependulum")
    planner = builder.make_planner(cfg, spec, torch.device("cpu"))  # the gains box +-10, std 1 at every plan
    assert planner.horizon == 3 and planner.low.tolist() == [-10.0] and planner.init_std == 1.0
    cfg.planner.name = "mppi"  # mppi's sigma is in half-ranges of the box
    assert builder.make_planner(cfg, spec, torch.device("cpu")).sigma == pytest.approx(0.1)
    bad = [
        (["planner.name=icem"], "needs planner.name cem or mppi"),
        (["planner.replan_every=2"], "planner.replan_every must be 1"),
        (["planner.feedback.gain_std=0"], "gain_std must be a finite number > 0"),
        (["planner.feedback.features=[0]", "planner.feedback.scale=[1, 2]"], "one finite value > 0 per feature"),
        (["planner.feedback.features=[0, 1"], "is not a list"),
    ]
    for extra, message in bad:
        with pytest.raises(ConfigError, match=message):
            make_config(
                "inverteddoublependulum", "gem", "fast", parse_overrides(["planner.candidates=feedback", *extra])
            )
    cfg = make_config(
        "reacher", "delta", "fast", parse_overrides(["planner.candidates=feedback", "planner.feedback.features=[99]"])
    )
    with pytest.raises(ConfigError, match="reacher has 10 observations"):
        builder.make_feedback(cfg, envs.get("reacher"), torch.device("cpu"))


def test_a_feedback_run_resumes_with_its_fitted_scale_and_matches_an_uninterrupted_run(tmp_path) -> None:
    common = [
        sys.executable, str(ROOT / "run_pets.py"), "--env", "inverteddoublependulum", "--model", "gem",
        "--preset", "fast", *TINY_PLANNER, *TINY_MODEL, "episode_length=30", "seed_steps=100", "threads=1",
        "--quiet", "planner.feedback.features=null", "planner.feedback.scale=null",  # all 11, the scale fitted
    ]  # fmt: skip
    ref, resumed = tmp_path / "ref", tmp_path / "resumed"
    subprocess.run([*common, "--trials", "3", "--out", str(ref)], check=True, cwd=ROOT, capture_output=True)
    subprocess.run([*common, "--trials", "2", "--out", str(resumed)], check=True, cwd=ROOT, capture_output=True)
    state = torch.load(resumed / "checkpoint.pt", weights_only=False)
    assert state["feedback"]["scale"].shape == (11,) and (state["feedback"]["scale"] != 1).all()
    subprocess.run(
        [sys.executable, str(ROOT / "run_pets.py"), "--resume", str(resumed), "--trials", "3", "--quiet"],
        check=True,
        cwd=ROOT,
        capture_output=True,
    )
    key = [line.split(",")[2:4] for line in (ref / "metrics.csv").read_text().splitlines()]
    assert key == [line.split(",")[2:4] for line in (resumed / "metrics.csv").read_text().splitlines()]
    assert len(key) == 4


def test_open_loop_replay_of_a_feedback_run_plans_action_sequences() -> None:
    """pets.openloop plans one action sequence per episode: a run made with feedback candidates (IDP's fast preset)
    is replayed with open-loop candidates of --steps actions, and asking for feedback there is an error."""
    from pets.planning.openloop import planning_config

    run_cfg = make_config("inverteddoublependulum", "gem", "fast")
    assert run_cfg.planner.candidates == "feedback"
    cfg = planning_config(run_cfg, "cem", 25)
    assert cfg.planner.candidates == "open_loop" and cfg.planner.horizon == 25
    spec, cpu = envs.get("inverteddoublependulum"), torch.device("cpu")
    agent = builder.make_agent(cfg, spec, make_model(cfg, spec, cpu), cpu, torch.Generator())
    assert agent.feedback is None and agent.planner.horizon == 25
    with pytest.raises(ConfigError, match="planner.candidates is set by open-loop planning itself"):
        planning_config(run_cfg, "cem", 25, {"planner.candidates": "feedback"})
    # closed loop: a research-planner run given IDP's feedback planner as text overrides (lists included)
    research = make_config("inverteddoublependulum", "gem", "research")
    text = {"planner.candidates": "feedback", "planner.horizon": "60", "planner.feedback.features": "[0,1,2,5,6,7]",
            "planner.feedback.scale": "[0.5,0.2,0.2,1.0,2.0,2.0]", "planner.propagation": "members"}  # fmt: skip
    closed = planning_config(research, "cem", 300, text, closed=True)
    assert closed.planner == make_config("inverteddoublependulum", "gem", "research", text).planner
    assert list(closed.planner.feedback.features) == [0, 1, 2, 5, 6, 7] and closed.planner.horizon == 60
    with pytest.raises(ConfigError, match="bad value for planner.feedback.features"):
        planning_config(research, "cem", 300, {"planner.feedback.features": "[0, 1"}, closed=True)


def test_the_benchmark_compares_the_planners_that_search_gains() -> None:
    """pets.bench --compare on a feedback config (IDP's fast preset): no iCEM rows (refused by the config), the
    configured path marked default, and every row's config valid."""
    from pets.bench import _row_config, compare_rows

    cfg = make_config("inverteddoublependulum", "gem", "fast", {"planner.precision": "bf16"})
    rows = compare_rows(cfg)
    assert [planner["name"] for _, planner in rows] == ["cem", "cem", "cem", "cem", "mppi", "cem"]
    assert [label for label, _ in rows if label.startswith("default: ")] == ["default: cem bf16 eager"]
    for _, planner in rows:
        assert _row_config(cfg, planner).planner.candidates == "feedback"
