"""The --model variants (pets/models.py, gem_head/two_stage.py): delta-det, gem2, delta-groupfeat next to delta, gem.

Ground truth: real MuJoCo transitions (pets.collect), scipy rotations for the SO(3) Frobenius loss, closed-form
2x2 rotations for SO(2), numpy for the squared errors; the CLIs end to end in subprocesses (one torch thread).
"""

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import envs
from dynamics.heads import DeltaHead, DeterministicDeltaHead
from dynamics.model import DynamicsModel
from dynamics.networks import DETERMINISTIC_LOGVAR, DeterministicEnsemble, GaussianEnsemble
from envs.layout import Group, ObsLayout
from gem_head.ablation import GroupFeatureDeltaHead
from gem_head.head import GemHead
from gem_head.se_root import GemSEHead
from gem_head.two_stage import TwoStageGemEnsemble, TwoStageGemHead
from pets import builder
from pets.config import HEADS, make_config
from pets.data.collect import collect
from pets.data.datasets import save_dataset, transitions
from pets.learning.evaluation import evaluate
from pets.learning.offline import train_offline
from pets.learning.trainer import ModelTrainer
from pets.models import MODELS, make_model, models_for
from pets.planning.propagation import TrajectoryEvaluator
from pets.runs import rundir
from tests.tiny import TINY_PLANNER

ROOT = Path(__file__).resolve().parents[1]
#: Models without a predictive variance (MSE / Frobenius training, zero sampling noise).
DETERMINISTIC = tuple(name for name, entry in MODELS.items() if entry.deterministic)
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
CPU = torch.device("cpu")
SMALL = {
    "model.hidden_size": 32,
    "model.num_layers": 2,
    "model.ensemble_size": 3,
    "model.num_elites": 2,
    "model.batch_size": 32,
    "device": "cpu",
}
TINY_MODEL = [
    "model.hidden_size=16",
    "model.num_layers=2",
    "model.ensemble_size=2",
    "model.num_elites=2",
    "model.batch_size=32",
]


pytestmark = pytest.mark.usefixtures("single_thread")


_DATA: dict = {}


def data(env: str, episodes: int = 3, steps: int = 40) -> dict:
    """Real transitions (random policy) of ``env``, cached per process."""
    key = (env, episodes, steps)
    if key not in _DATA:
        _DATA[key] = collect(envs.get(env), "random", episodes, seed=0, max_steps=steps)
    return _DATA[key]


def tensors(env: str, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return tuple(torch.as_tensor(x, dtype=dtype) for x in transitions(data(env)))


def build(env: str, head_name: str, seed: int = 0, **overrides):
    cfg = make_config(env, head_name, "fast", {**SMALL, **overrides})
    spec = envs.get(env)
    torch.manual_seed(seed)
    model = make_model(cfg, spec, CPU)
    head, ens = model.head, model.network
    return cfg, spec, head, ens


# --------------------------------------------------------------------------- every model
@pytest.mark.parametrize(
    "env, head_name",
    [(env, head) for env in ("invertedpendulum", "reacher", "ant") for head in models_for(envs.get(env))],
)
def test_every_model_builds_trains_and_plans(env, head_name):
    cfg, spec, head, ens = build(env, head_name, **{"model.max_epochs": 20, "model.patience": 20, "model.lr": 3e-3})
    kinds = {
        "delta": (DeltaHead, GaussianEnsemble),
        "gem": (GemHead, GaussianEnsemble),
        "delta-det": (DeterministicDeltaHead, DeterministicEnsemble),
        "gem2": (TwoStageGemHead, TwoStageGemEnsemble),
        "delta-groupfeat": (GroupFeatureDeltaHead, GaussianEnsemble),
        "gem-se": (GemSEHead, GaussianEnsemble),
    }
    assert isinstance(head, kinds[head_name][0]) and type(ens) is kinds[head_name][1] and head.name == head_name
    assert head.deterministic == ens.deterministic == (head_name in DETERMINISTIC)
    assert cfg.planner.propagation == ("expectation" if head_name in DETERMINISTIC else "tsinf")
    obs, act, next_obs = tensors(env)
    trainer = builder.make_trainer(cfg, DynamicsModel(head, ens))
    x = head.inputs(obs, act)
    trainer.fit_error_scale(obs, next_obs)
    before = trainer.evaluate(x, obs, next_obs)  # (E,) holdout criterion of the untrained members
    result = trainer.train(obs, act, next_obs, torch.Generator().manual_seed(1))
    assert math.isfinite(result.train_loss) and math.isfinite(result.val_loss) and result.epochs >= 1
    assert result.val_loss < result.initial_val_loss  # the selected members are trained ones
    assert ens.elites.numel() == 2
    assert float(trainer.evaluate(x, obs, next_obs).mean()) < float(before.mean())  # training moved towards the data
    for propagation in ("tsinf", "ts1", "expectation"):
        evaluator = TrajectoryEvaluator(
            DynamicsModel(head, ens), spec.reward, spec.terminated, particles=4, propagation=propagation
        )
        actions = torch.rand(6, 5, spec.act_dim, generator=torch.Generator().manual_seed(2)) * 2 - 1
        returns = evaluator(obs[0], actions, torch.Generator().manual_seed(3))
        assert returns.shape == (6,) and torch.isfinite(returns).all()


# --------------------------------------------------------------------------- delta-det
def test_deterministic_is_declared_by_head_and_network_and_they_agree_with_the_table():
    """The model table's flag (read without building, e.g. for the config's per-model defaults) is each built
    model's, and a head and a network that disagree are refused in one line."""
    from pets.models import MODELS

    for name, entry in MODELS.items():
        env = "ant" if entry.needs_root else "reacher"
        model = make_model(make_config(env, name, "fast"), envs.get(env), torch.device("cpu"))
        assert model.deterministic == model.head.deterministic == entry.deterministic == (name in DETERMINISTIC)
    layout = envs.get("reacher").layout
    head = DeterministicDeltaHead(layout, 2)
    with pytest.raises(ValueError, match="head 'delta-det' is deterministic but the network GaussianEnsemble is Gauss"):
        DynamicsModel(head, GaussianEnsemble(head.input_dim, head.target_dim, ensemble_size=2, hidden_size=8))


def test_deterministic_logvar_gives_exactly_zero_noise_in_every_dtype():
    for dtype in (torch.float16, torch.bfloat16, torch.float32, torch.float64):
        lv = torch.tensor(DETERMINISTIC_LOGVAR, dtype=dtype)
        assert torch.isfinite(lv) and torch.exp(0.5 * lv) == 0
        eps = torch.randn(1000, dtype=torch.float32).to(dtype)
        mean = torch.randn(1000, dtype=torch.float32).to(dtype)
        assert torch.equal(mean + torch.exp(0.5 * lv) * eps, mean)


@pytest.mark.parametrize("head_name", ["delta-det", "gem2"])
def test_deterministic_tsinf_rollouts_are_the_members_mean_paths(head_name):
    cfg, spec, head, ens = build("reacher", head_name, **{"model.max_epochs": 2})
    obs, act, next_obs = tensors("reacher")
    builder.make_trainer(cfg, DynamicsModel(head, ens)).train(obs, act, next_obs, torch.Generator().manual_seed(0))
    evaluator = TrajectoryEvaluator(
        DynamicsModel(head, ens), spec.reward, spec.terminated, particles=4, propagation="tsinf"
    )
    actions = torch.rand(3, 6, spec.act_dim, generator=torch.Generator().manual_seed(5)) * 2 - 1
    traj_a, rew_a = evaluator.rollout(obs[3], actions, torch.Generator().manual_seed(1))
    traj_b, rew_b = evaluator.rollout(obs[3], actions, torch.Generator().manual_seed(2))
    assert torch.equal(traj_a, traj_b) and torch.equal(rew_a, rew_b)  # the generator does not matter: no noise
    # every particle follows one elite member's mean path, computed here step by step without any sampling
    elites = ens.elites
    with torch.no_grad():
        paths = []
        for k in range(elites.numel()):
            o = obs[3].expand(3, -1)
            path = [o]
            for t in range(actions.shape[1]):
                mean, logvar = ens(head.inputs(o, actions[:, t]), elites[k : k + 1])
                assert (logvar == DETERMINISTIC_LOGVAR).all()
                o = head.next_obs(o, mean[0])
                path.append(o)
            paths.append(torch.stack(path, dim=1))  # (N, H + 1, obs_dim)
    for n in range(3):
        for p in range(4):
            err = [float((traj_a[n, p] - paths[k][n]).abs().max()) for k in range(elites.numel())]
            assert min(err) < 1e-5, err
    # with one member, ts-inf, ts1 and expectation all give the mean path
    cfg1, spec, head1, ens1 = build("reacher", head_name, **{"model.ensemble_size": 1, "model.num_elites": 1})
    ens1.fit_normaliser(head1.inputs(obs, act))
    traj = {
        m: TrajectoryEvaluator(
            DynamicsModel(head1, ens1), spec.reward, spec.terminated, particles=3, propagation=m
        ).rollout(obs[3], actions, torch.Generator().manual_seed(0))[0]
        for m in ("tsinf", "ts1", "expectation")
    }
    torch.testing.assert_close(traj["tsinf"], traj["expectation"], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(traj["ts1"], traj["expectation"], rtol=1e-6, atol=1e-6)


def test_delta_det_mse_training_learns_a_known_function():
    layout = ObsLayout(obs_dim=2, groups=(Group("x", "Rn", (0, 1)),))
    head = DeterministicDeltaHead(layout, act_dim=1)
    g = torch.Generator().manual_seed(0)
    obs, act = torch.rand(2000, 2, generator=g) * 4 - 2, torch.rand(2000, 1, generator=g) * 2 - 1
    delta = torch.stack([torch.sin(obs[:, 0]) * act[:, 0], 0.5 * obs[:, 1] - 0.3 * act[:, 0] ** 2], dim=1)
    next_obs = obs + delta
    # the loss is the per-member mean squared error and ignores the log-variance
    mean, target = torch.randn(3, 5, 2, generator=g), torch.randn(3, 5, 2, generator=g)
    want = torch.tensor([float(np.mean((target[e].numpy() - mean[e].numpy()) ** 2)) for e in range(3)])
    torch.testing.assert_close(head.loss(mean, torch.randn(3, 5, 2), target, None, None), want)
    torch.manual_seed(0)
    ens = DeterministicEnsemble(head.input_dim, head.target_dim, ensemble_size=2, hidden_size=32, num_layers=2)
    trainer = ModelTrainer(
        DynamicsModel(head, ens), lr=3e-3, batch_size=64, max_epochs=30, patience=30, holdout_ratio=0.0
    )
    x = head.inputs(obs, act)
    ens.fit_normaliser(x)
    trainer.fit_error_scale(obs, next_obs)
    before = trainer.evaluate(x, obs, next_obs)
    trainer.train(obs, act, next_obs, torch.Generator().manual_seed(1))
    after = trainer.evaluate(x, obs, next_obs)
    assert (after < 0.02 * before).all(), (before, after)
    with torch.no_grad():
        pred = head.next_obs(obs[:5], ens(x[:5])[0].mean(0))
    torch.testing.assert_close(pred, next_obs[:5], atol=0.05, rtol=0)


# --------------------------------------------------------------------------- gem2
def test_gem2_velocity_network_receives_the_predicted_coefficients():
    cfg, spec, head, ens = build("ant", "gem2")
    obs, act, next_obs = tensors("ant")
    ens.fit_normaliser(head.inputs(obs, act))
    ens.fit_target_normaliser(head.targets(obs, next_obs))
    h = ens.normalise(head.inputs(obs[:8], act[:8]))
    alpha = ens.coefficient_net(h, None).detach().requires_grad_(True)
    dv = ens.velocity_net(h, alpha, None)
    (grad,) = torch.autograd.grad(dv.sum(), alpha)
    assert grad.shape == alpha.shape and (grad.abs().sum(-1) > 0).all()
    # forward wires it: changing only the coefficient network's output bias changes the velocity slots
    vs, gs = list(head.velocity_slots), list(head.group_slots)
    with torch.no_grad():
        before = ens(head.inputs(obs[:8], act[:8]))[0]
        ens.coef_biases[-1].add_(0.3)  # standardised units
        after = ens(head.inputs(obs[:8], act[:8]))[0]
    torch.testing.assert_close(after[..., gs], before[..., gs] + 0.3 * ens.target_std[gs])
    assert ((after[..., vs] - before[..., vs]).abs() > 0).any(-1).all()
    # Algorithm 1 steps both networks along the total loss: the velocity loss alone reaches the coefficient net
    ens.zero_grad()
    mean, logvar = ens(head.inputs(obs[:8], act[:8]).expand(ens.ensemble_size, -1, -1))
    target = head.targets(obs[:8], next_obs[:8]).expand_as(mean)
    (mean[..., vs] - target[..., vs]).square().sum().backward()
    assert ens.coef_weights[0].grad.abs().sum() > 0


@pytest.mark.parametrize("env", ["invertedpendulum", "reacher", "halfcheetah", "ant"])
def test_gem2_output_is_gemhead_target_order(env):
    cfg, spec, head, ens = build(env, "gem2")
    obs, act, next_obs = tensors(env, torch.float64)
    ens = ens.double()
    true = head.targets(obs, next_obs)
    gs, vs = list(head.group_slots), list(head.velocity_slots)
    assert sorted(gs + vs) == list(range(head.target_dim))
    layout = spec.layout
    rn = {f"d {g.name}[{k}]" for g in layout.groups if g.kind == "Rn" for k in range(len(g.indices))}
    size = {"Rn": None, "SO2_angle": 1, "SO2_cossin": 1, "SO3_quat": 3}
    assert len(gs) == sum(size[g.kind] or len(g.indices) for g in layout.groups)
    assert all(head.target_names[i] in rn or head.target_names[i].startswith("alpha ") for i in gs)
    dynamic = {f"d vel[{j}]" for j in layout.velocities} | {f"d other[{j}]" for j in layout.other}
    assert {head.target_names[i] for i in vs} == dynamic
    assert torch.equal(ens.assemble(true[:, gs], true[:, vs]), true)
    # replace both networks by the truth: forward gives GemHead's targets and GemHead.next_obs the next state
    m = ens.ensemble_size
    ens.coefficient_net = lambda h, idx: true[:, gs].expand(m, -1, -1)
    ens.velocity_net = lambda h, alpha, idx: true[:, vs].expand(m, -1, -1)
    mean, logvar = ens(head.inputs(obs, act))
    assert torch.equal(mean, true.expand(m, -1, -1)) and (logvar == DETERMINISTIC_LOGVAR).all()
    # exact up to float64 rounding (obs + (next - obs), exp(log(q0^* q1)) composed with q0, ...); derived carried
    pred, derived = list(layout.predicted_indices), list(layout.derived)
    torch.testing.assert_close(head.next_obs(obs, mean[1])[:, pred], next_obs[:, pred], rtol=0, atol=1e-12)
    assert torch.equal(head.next_obs(obs, mean[1])[:, derived], obs[:, derived])


def _so2(theta: float) -> np.ndarray:
    return np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])


def test_gem2_loss_equals_the_hand_computed_frobenius_plus_velocity_mse_so2():
    # InvertedPendulum's layout: cart (Rn), hinge (SO2 angle), 2 velocities; targets [d cart, alpha, d v0, d v1]
    spec = envs.get("invertedpendulum")
    head = TwoStageGemHead(spec.layout, spec.act_dim)
    obs = torch.tensor([[0.1, 0.3, -0.2, 1.0], [-0.5, 3.0, 0.4, -2.0]], dtype=torch.float64)
    next_obs = torch.tensor([[0.12, 0.35, -0.1, 0.7], [-0.45, 3.3, 0.5, -2.5]], dtype=torch.float64)
    mean = torch.tensor([[[0.01, 0.07, 0.2, -0.1], [0.06, 0.25, 0.0, -0.4]]], dtype=torch.float64)
    target = head.targets(obs, next_obs)
    got = head.loss(mean, torch.zeros_like(mean), target.unsqueeze(0), obs.unsqueeze(0), next_obs.unsqueeze(0))
    per = []
    for b in range(2):
        o, o2, mu = obs[b].numpy(), next_obs[b].numpy(), mean[0, b].numpy()
        frob = np.sum((_so2(mu[1]) @ _so2(o[1]) - _so2(o2[1])) ** 2)  # ||exp(alpha_hat) G_t - G_{t+1}||_F^2
        cart = (mu[0] - (o2[0] - o[0])) ** 2
        vel = np.sum((mu[2:] - (o2[2:] - o[2:])) ** 2)  # ||dv_hat - dv||^2
        per.append((frob + cart + vel) / 4)
    torch.testing.assert_close(got, torch.tensor([np.mean(per)], dtype=torch.float64), rtol=1e-12, atol=0)
    # the logvar does not enter
    assert torch.equal(
        got, head.loss(mean, torch.randn_like(mean), target.unsqueeze(0), obs.unsqueeze(0), next_obs.unsqueeze(0))
    )


@pytest.mark.parametrize("compose", ["right", "left"])
def test_gem2_loss_equals_the_hand_computed_frobenius_plus_velocity_mse_so3(compose):
    layout = ObsLayout(
        obs_dim=9,
        groups=(Group("pos", "Rn", (0, 1)), Group("q", "SO3_quat", (2, 3, 4, 5))),
        velocities=(6, 7),
        other=(8,),
    )
    head = TwoStageGemHead(layout, act_dim=1, compose=compose)
    assert head.group_slots == (0, 1, 2, 3, 4) and head.velocity_slots == (5, 6, 7)
    rng = np.random.default_rng(0)
    r0, r1 = Rotation.random(3, random_state=1), Rotation.random(3, random_state=2)
    obs, next_obs = rng.normal(size=(3, 9)), rng.normal(size=(3, 9))
    obs[:, 2:6], next_obs[:, 2:6] = r0.as_quat(scalar_first=True), r1.as_quat(scalar_first=True)
    mean = rng.normal(size=(1, 3, 8)) * 0.5
    t = torch.as_tensor
    target = head.targets(t(obs), t(next_obs))
    got = head.loss(t(mean), t(mean) * 0, target[None], t(obs)[None], t(next_obs)[None])
    per = []
    for b in range(3):
        step = Rotation.from_rotvec(mean[0, b, 2:5]).as_matrix()
        g0, g1 = r0[b].as_matrix(), r1[b].as_matrix()
        pred = g0 @ step if compose == "right" else step @ g0
        frob = np.sum((pred - g1) ** 2)
        rn = np.sum((mean[0, b, :2] - (next_obs[b, :2] - obs[b, :2])) ** 2)
        vel = np.sum((mean[0, b, 5:] - (next_obs[b, 6:] - obs[b, 6:])) ** 2)  # velocities and the other entry
        per.append((frob + rn + vel) / 8)
    torch.testing.assert_close(got, torch.tensor([np.mean(per)], dtype=torch.float64), rtol=1e-10, atol=0)


def test_gem2_state_dict_round_trip_keeps_the_target_normaliser():
    cfg, spec, head, ens = build("reacher", "gem2")
    obs, act, next_obs = tensors("reacher")
    builder.make_trainer(cfg, DynamicsModel(head, ens)).train(obs, act, next_obs, torch.Generator().manual_seed(0))
    y = head.targets(obs, next_obs)
    torch.testing.assert_close(ens.target_mean, y.double().mean(0).float())  # set by ModelTrainer
    std = y.double().std(0, correction=0)
    assert (std < 1e-5).any()  # the target position never moves within an episode: its std is taken as 1
    torch.testing.assert_close(ens.target_std, torch.where(std < 1e-5, 1.0, std).float())
    _, _, _, fresh = build("reacher", "gem2", seed=9)
    fresh.load_state_dict(ens.state_dict())
    x = head.inputs(obs, act)
    with torch.no_grad():
        assert torch.equal(fresh(x)[0], ens(x)[0]) and torch.equal(fresh.elites, ens.elites)
    with pytest.raises(ValueError, match="split range"):
        TwoStageGemEnsemble(4, 3, (0, 1), (1, 2))


# --------------------------------------------------------------------------- delta-groupfeat
@pytest.mark.parametrize("env", ["reacher", "ant", "inverteddoublependulum"])
def test_groupfeat_inputs_are_gem_inputs_and_targets_are_delta_targets(env):
    spec = envs.get(env)
    obs, act, next_obs = tensors(env)
    head, gem, delta = (
        GroupFeatureDeltaHead(spec.layout, spec.act_dim),
        GemHead(spec.layout, spec.act_dim),
        DeltaHead(spec.layout, spec.act_dim),
    )
    assert head.input_dim == gem.input_dim and head.input_names == gem.input_names
    assert torch.equal(head.inputs(obs, act), gem.inputs(obs, act))
    assert head.target_dim == delta.target_dim == len(spec.layout.predicted_indices)
    assert torch.equal(head.targets(obs, next_obs), delta.targets(obs, next_obs))
    step = delta.targets(obs, next_obs)
    assert torch.equal(head.next_obs(obs, step), delta.next_obs(obs, step))
    assert not head.deterministic


def test_groupfeat_equals_gem_on_a_planar_env():
    """HalfCheetah: every group Rn or SO2_angle, so GemHead's targets are next_obs - obs (no step wraps an angle)."""
    obs, act, next_obs = tensors("halfcheetah")
    runs = {}
    for name in ("gem", "delta-groupfeat"):
        cfg, spec, head, ens = build("halfcheetah", name, seed=4, **{"model.max_epochs": 3})
        assert torch.equal(head.inputs(obs, act), GemHead(spec.layout, spec.act_dim).inputs(obs, act))
        result = builder.make_trainer(cfg, DynamicsModel(head, ens)).train(
            obs, act, next_obs, torch.Generator().manual_seed(5)
        )
        runs[name] = (head, ens, result)
    (gh, ge, gr), (fh, fe, fr) = runs["gem"], runs["delta-groupfeat"]
    assert torch.equal(gh.targets(obs, next_obs), fh.targets(obs, next_obs))
    assert gr == fr and torch.equal(ge.elites, fe.elites)
    x = gh.inputs(obs, act)
    with torch.no_grad():
        (gm, glv), (fm, flv) = ge(x), fe(x)
    assert torch.equal(gm, fm) and torch.equal(glv, flv)
    assert torch.equal(gh.next_obs(obs, gm.mean(0)), fh.next_obs(obs, fm.mean(0)))


# --------------------------------------------------------------------------- offline pipeline, in process
@pytest.mark.parametrize(
    "env, head_name", [("reacher", head) for head in models_for(envs.get("reacher"))] + [("hopper", "gem-se")]
)
def test_offline_train_and_evaluate_every_model(env, head_name, tmp_path):
    arrays = data(env, episodes=4, steps=30)
    extra = {"model.ensemble_size": 1, "model.num_elites": 1} if head_name in DETERMINISTIC else {}
    out = train_offline(
        arrays, head_name, tmp_path / "run", {**dict(SMALL), **extra}, preset="fast", seed=0, device="cpu", epochs=3
    )
    cfg, spec, model = builder.load_model(out)
    head, ens = model.head, model.network
    assert cfg.head == head_name and head.name == head_name and ens.deterministic == (head_name in DETERMINISTIC)
    results = {
        mode: evaluate(out, arrays, horizons=(1, 5, 10), starts=20, mode=mode, device="cpu", log=lambda m: 0)
        for mode in ("mean", "sample")
    }
    for res in results.values():
        assert res["model"] == head_name
        for row in res["horizons"].values():
            assert math.isfinite(row["mean_step_error"]) and row["nonfinite_fraction"] == 0
    if head_name in DETERMINISTIC:  # one member, no noise: sampling is the mean prediction
        assert results["mean"]["horizons"] == results["sample"]["horizons"]
        o = torch.as_tensor(arrays["obs"][:2, 0], dtype=torch.float32)
        a = torch.as_tensor(arrays["act"][:2, :6], dtype=torch.float32)
        assert torch.equal(
            DynamicsModel(head, ens).rollout(o, a, "mean"),
            DynamicsModel(head, ens).rollout(o, a, "sample", torch.Generator().manual_seed(3)),
        )


# --------------------------------------------------------------------------- config and CLIs
def test_config_heads_and_deterministic_defaults():
    assert set(HEADS) == {"delta", "gem", "delta-det", "gem2", "delta-groupfeat", "gem-se"}
    for name in HEADS:
        cfg = make_config("halfcheetah", name)
        assert cfg.head == name
        assert cfg.planner.propagation == ("expectation" if name in DETERMINISTIC else "tsinf")
    assert make_config("hopper", "gem2", overrides={"planner.propagation": "tsinf"}).planner.propagation == "tsinf"
    assert make_config("hopper", "delta", overrides={"head": "delta-det"}).planner.propagation == "expectation"
    from pets.config import ConfigError

    with pytest.raises(ConfigError, match="delta-groupfeat"):
        make_config("hopper", "gem3")


def _cli(args: list) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, *map(str, args)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV
    )


def _wait(procs: dict, timeout: int = 240) -> dict:
    out = {}
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=timeout)
        assert proc.returncode == 0, f"{name}: exit {proc.returncode}\n{stdout}\n{stderr}"
        out[name] = stdout
    return out


def test_cli_end_to_end_delta_det_and_gem2(tmp_path, capsys):
    npz = save_dataset(tmp_path / "ip.npz", collect(envs.get("invertedpendulum"), "random", 5, seed=1))
    tiny_run = [
        "--preset",
        "fast",
        *TINY_PLANNER,
        "model.max_epochs=2",
        "episode_length=15",
        "seed_steps=60",
        *TINY_MODEL,
        "--quiet",
    ]
    train_args = {
        m: [
            "--data",
            str(npz),
            "--model",
            m,
            "--out",
            str(tmp_path / m),
            "--epochs",
            "3",
            "--device",
            "cpu",
            "--quiet",
            *TINY_MODEL,
        ]
        for m in ("delta-det", "gem2")
    }
    proc = _cli(["-m", "pets.train", *train_args["gem2"]])  # the real command, in a subprocess
    import run_pets
    from pets.tools.train import main as train_main

    # meanwhile, in this process: the same CLI entry point for delta-det, and run_pets.py --model gem2 (1 trial)
    capsys.readouterr()
    assert train_main(train_args["delta-det"]) == 0
    out = {"delta-det": capsys.readouterr().out}
    assert (
        run_pets.main(
            [
                "--model",
                "gem2",
                "--env",
                "invertedpendulum",
                "--trials",
                "1",
                "--out",
                str(tmp_path / "online"),
                *tiny_run,
            ]
        )
        == 0
    )
    out.update(_wait({"gem2": proc}))
    for m in ("delta-det", "gem2"):
        assert f"{m} model trained on" in out[m]
        res = evaluate(tmp_path / m, npz, horizons=(1, 3), starts=20, device="cpu", log=lambda message: None)
        assert res["model"] == m and all(math.isfinite(r["mean_step_error"]) for r in res["horizons"].values())
        cfg, spec, model = builder.load_model(tmp_path / m)
        assert cfg.head == m and model.deterministic and model.ensemble_size == 2
    # the online run: one trial of PETS with the two-stage GEM, expectation propagation by default
    online = tmp_path / "online"
    rows = rundir.read_metrics(online / rundir.METRICS_FILE)
    assert len(rows) == 1 and math.isfinite(rows[0]["episode_reward"]) and rows[0]["episode_reward"] >= 1
    cfg, spec, model = builder.load_model(online)
    ens = model.network
    assert cfg.head == "gem2" and cfg.planner.propagation == "expectation" and isinstance(ens, TwoStageGemEnsemble)
    # a bad --model is one line naming the accepted ones, exit 2 (pets.train and run_pets.py)
    for main, args in (
        (train_main, ["--data", str(npz), "--model", "gem3", "--out", str(tmp_path / "bad")]),
        (run_pets.main, ["--model", "gem3", "--env", "hopper"]),
    ):
        capsys.readouterr()
        with pytest.raises(SystemExit) as exc:
            main(args)
        err = capsys.readouterr().err.strip()
        assert exc.value.code == 2 and "delta-groupfeat" in err and len(err.splitlines()) == 1, err


def test_a_run_with_relu_records_it_and_reloads_the_same_network(tmp_path, capsys):
    """model.activation=relu end to end: the run's config.yaml records it and the reloaded model has it; a
    config.yaml from before the key existed loads as SiLU (what every such run used); an unknown activation is one
    line, exit 2, and no run directory."""
    from omegaconf import OmegaConf

    import run_pets
    from pets.config import load_config
    from tests.test_cli import TINY

    out = tmp_path / "relu"
    assert (
        run_pets.main(
            ["--env", "reacher", "--trials", "1", "--out", str(out), "--quiet", *TINY, "model.activation=relu"]
        )
        == 0
    )
    assert "activation: relu" in (out / "config.yaml").read_text()
    cfg, spec, model = builder.load_model(out)
    assert cfg.model.activation == model.network.activation == "relu"
    stored = OmegaConf.to_container(OmegaConf.load(out / "config.yaml"))
    del stored["model"]["activation"]
    (tmp_path / "old.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(stored)))
    assert load_config(str(tmp_path / "old.yaml")).model.activation == "silu"
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        run_pets.main(["--env", "reacher", "--out", str(tmp_path / "bad"), "model.activation=tanh"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "model.activation must be one of silu, relu, got 'tanh'" in err
    assert err.count("\n") == 1 and not (tmp_path / "bad").exists()


def test_a_deterministic_model_registered_from_outside_gets_the_deterministic_defaults(request):
    """A model registered as deterministic after pets.config is imported plans by expectation by default, as
    delta-det and gem2 do (the per-model defaults were a table made at import: it got ts1); a given propagation
    still wins, and a probabilistic one keeps the preset's."""
    from pets.models import ModelEntry, register_model

    request.addfinalizer(lambda: MODELS.pop("mydet", None))
    det = MODELS["delta-det"]
    register_model("mydet", ModelEntry("delta-det under my name", True, det.make_head, det.make_network))
    assert make_config("invertedpendulum", "mydet").planner.propagation == "expectation"
    assert make_config("invertedpendulum", "delta-det").planner.propagation == "expectation"
    given = make_config("invertedpendulum", "mydet", overrides={"planner.propagation": "tsinf"})
    assert given.planner.propagation == "tsinf"
    assert make_config("invertedpendulum", "delta").planner.propagation != "expectation"  # the preset's (tsinf)


def test_a_model_registered_from_outside_is_a_model_name_everywhere(tmp_path, monkeypatch, request):
    """register_model after pets.config is imported (was: only MODELS edited before that import took, as HEADS was
    a tuple made at import): the config, run_pets.py in the process and the study arguments accept the name; a
    taken name, a name the command line cannot carry and an entry of another type are refused in one line."""
    import run_pets
    from pets.experiments.arguments import parse_models
    from pets.models import ModelEntry, gaussian_ensemble, register_model
    from tests.test_cli import TINY

    entry = ModelEntry("delta under my name", False, MODELS["delta"].make_head, gaussian_ensemble)
    assert "mine" not in HEADS
    request.addfinalizer(lambda: MODELS.pop("mine", None))  # removed again after the test
    assert register_model("mine", entry) is entry and "mine" in HEADS and MODELS["mine"] is entry
    assert make_config("invertedpendulum", "mine").head == "mine" and parse_models("delta,mine") == ["delta", "mine"]
    out = tmp_path / "run"
    args = ["--env", "invertedpendulum", "--model", "mine", "--trials", "1", "--out", str(out), *TINY]
    assert run_pets.main(args) == 0
    assert "head: mine" in (out / "config.yaml").read_text()
    assert builder.load_model(out)[2].name == "mine"  # the registered name, not the reused head's ("delta")
    for name, bad, message in (
        ("delta", entry, "model name 'delta' is taken"),
        ("my model", entry, "without spaces"),
        ("my/model", entry, "'/'"),  # run directories are named by it
        ("mine2", MODELS["delta"].make_head, "entry must be a pets.models.ModelEntry"),
    ):
        with pytest.raises(ValueError, match=message) as err:
            register_model(name, bad)
        assert "\n" not in str(err.value)
    assert MODELS["delta"].summary.startswith("PETS")

    class ShortDecode(DeltaHead):  # next_obs one entry short: was a RuntimeError deep in the first training
        def next_obs(self, obs, target):
            return super().next_obs(obs, target)[..., :-1]

    short = ModelEntry("a head that decodes one entry short", False, lambda cfg, spec: ShortDecode(spec.layout,
                       spec.act_dim), gaussian_ensemble)  # fmt: skip
    monkeypatch.setitem(MODELS, "short", short)
    spec = envs.get("invertedpendulum")
    with pytest.raises(ValueError, match=r"model 'short': its head's next_obs returned \(2, 3\) .* not \(2, 4\)"):
        make_model(make_config("invertedpendulum", "short"), spec, torch.device("cpu"))

    class UnitQuaternionInputs(DeltaHead):  # defined only on valid observations: the probe must be one
        def inputs(self, obs, act):
            q = obs[..., 3:7]
            if not torch.all(q.norm(dim=-1) > 0.5):
                raise ValueError("not a unit quaternion")
            return super().inputs(obs, act)

    quat = ModelEntry("reads Ant's torso quaternion", False, lambda cfg, spec: UnitQuaternionInputs(spec.layout,
                      spec.act_dim), gaussian_ensemble)  # fmt: skip
    monkeypatch.setitem(MODELS, "quat", quat)
    make_model(make_config("ant", "quat"), envs.get("ant"), torch.device("cpu"))  # was: refused (zeros probe)


@pytest.mark.parametrize(
    ("make_head", "make_network", "deterministic", "message"),
    [
        (lambda cfg, spec: None, "gaussian", False, "make_head returned NoneType, not a dynamics.heads.DynamicsHead"),
        (lambda cfg, spec: DeltaHead(spec.layout, spec.act_dim), "deterministic", False,
         "head 'delta' is Gaussian but the network DeterministicEnsemble is deterministic"),
        (lambda cfg, spec: DeltaHead(spec.layout, spec.act_dim), "gaussian", True,
         "its ModelEntry says deterministic=True, but its head and network are not deterministic"),
    ],
)  # fmt: skip
def test_an_entry_whose_parts_do_not_fit_is_one_line_and_exit_2(
    make_head, make_network, deterministic, message, tmp_path, monkeypatch, capsys
) -> None:
    """A ModelEntry of one's own whose make_head returns no head, whose head and network disagree on being
    deterministic, or whose flag is not what it builds: one line naming the model, exit 2 and no run directory (was
    a traceback and exit 1)."""
    import run_pets
    from pets.models import ModelEntry, deterministic_ensemble, gaussian_ensemble
    from tests.test_cli import TINY

    network = {"gaussian": gaussian_ensemble, "deterministic": deterministic_ensemble}[make_network]
    monkeypatch.setitem(MODELS, "unfit", ModelEntry("parts that do not fit", deterministic, make_head, network))
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        run_pets.main(["--env", "invertedpendulum", "--model", "unfit", "--trials", "1", "--out", str(out), *TINY])
    assert exit_.value.code == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line and not line.startswith("run directory:")]
    assert len(lines) == 1 and f"model 'unfit': {message}" in lines[0] and not out.exists()
