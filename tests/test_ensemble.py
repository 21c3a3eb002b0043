"""Tests of the batched Gaussian ensemble (dynamics/networks.py)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from dynamics.losses import gaussian_nll
from dynamics.networks import GaussianEnsemble

IN, OUT, E = 5, 3, 4


pytestmark = pytest.mark.usefixtures("single_thread")


def make(**kw) -> GaussianEnsemble:
    torch.manual_seed(0)
    kw = {"ensemble_size": E, "hidden_size": 32, **kw}
    return GaussianEnsemble(IN, OUT, **kw)


def single_member_reference(ens: GaussianEnsemble, k: int, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Member k evaluated as an ordinary MLP with torch.nn.functional.linear, layer by layer."""
    h = (x - ens.input_mean) / ens.input_std
    n = len(ens.weights)
    for i, (w, b) in enumerate(zip(ens.weights, ens.biases)):
        h = F.linear(h, w[k].T, b[k, 0])
        if i < n - 1:
            h = h * torch.sigmoid(h)
    mean, lv = h[:, :OUT], h[:, OUT:]
    lv = ens.max_logvar - F.softplus(ens.max_logvar - lv)
    lv = ens.min_logvar + F.softplus(lv - ens.min_logvar)
    return mean, lv


def test_architecture_and_init() -> None:
    ens = GaussianEnsemble(IN, OUT)  # defaults: 7 members, 4 hidden layers of 200
    shapes = [tuple(w.shape) for w in ens.weights]
    assert shapes == [(7, IN, 200), (7, 200, 200), (7, 200, 200), (7, 200, 200), (7, 200, 2 * OUT)]
    assert ens.decays == [2.5e-5, 5e-5, 7.5e-5, 7.5e-5, 1e-4]
    assert all(torch.count_nonzero(b) == 0 for b in ens.biases)
    w = ens.weights[1]
    std = 1 / (2 * math.sqrt(200))
    assert w.abs().max() <= 2 * std + 1e-7  # truncated at two standard deviations
    assert 0.75 * std < w.std() < 0.95 * std  # a normal truncated at +-2 sigma has std 0.88 sigma
    assert torch.equal(ens.elites, torch.arange(7))
    assert torch.allclose(ens.max_logvar, torch.full((OUT,), 0.5))
    assert torch.allclose(ens.min_logvar, torch.full((OUT,), -10.0))


def test_output_shapes_shared_stacked_and_members() -> None:
    ens = make()
    x2 = torch.randn(9, IN)
    mean, lv = ens(x2)
    assert mean.shape == lv.shape == (E, 9, OUT)
    x3 = torch.randn(E, 9, IN)
    mean3, lv3 = ens(x3)
    assert mean3.shape == lv3.shape == (E, 9, OUT)
    # Shared inputs are the same as the stacked copy.
    m_rep, lv_rep = ens(x2.expand(E, 9, IN).contiguous())
    torch.testing.assert_close(mean, m_rep)
    torch.testing.assert_close(lv, lv_rep)
    # A subset of members, with shared and with per-member inputs, equals the full result indexed.
    members = torch.tensor([3, 1])
    ms, lvs = ens(x2, members)
    assert ms.shape == (2, 9, OUT)
    torch.testing.assert_close(ms, mean[members])
    torch.testing.assert_close(lvs, lv[members])
    ms3, lvs3 = ens(x3[members], members)
    torch.testing.assert_close(ms3, mean3[members])
    torch.testing.assert_close(lvs3, lv3[members])
    # Each member equals a plain per-member MLP.
    for k in range(E):
        rm, rlv = single_member_reference(ens, k, x3[k])
        torch.testing.assert_close(mean3[k], rm, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(lv3[k], rlv, rtol=1e-5, atol=1e-6)


def test_bad_inputs_raise() -> None:
    ens = make()
    with pytest.raises(ValueError, match="inputs must be"):
        ens(torch.randn(9, IN + 1))
    with pytest.raises(ValueError, match="inputs must be"):
        ens(torch.randn(E + 1, 9, IN))
    with pytest.raises(ValueError, match="inputs must be"):
        ens(torch.randn(E, 9, IN), torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="members"):
        ens(torch.randn(9, IN), torch.tensor([[0, 1]]))
    with pytest.raises(ValueError, match="fit_normaliser"):
        ens.fit_normaliser(torch.randn(9, IN, 1))
    with pytest.raises(ValueError, match="num_elites"):
        GaussianEnsemble(IN, OUT, ensemble_size=3, num_elites=4)
    with pytest.raises(ValueError, match="min_logvar"):
        GaussianEnsemble(IN, OUT, min_logvar=1.0, max_logvar=0.5)


def test_members_are_independent() -> None:
    ens = make()
    x = torch.randn(E, 16, IN)
    mean0, lv0 = ens(x)
    with torch.no_grad():
        for w in ens.weights:
            w[2] += 0.3 * torch.randn_like(w[2])
    mean1, lv1 = ens(x)
    others = [0, 1, 3]
    assert torch.equal(mean1[others], mean0[others])
    assert torch.equal(lv1[others], lv0[others])
    assert (mean1[2] - mean0[2]).abs().max() > 1e-3


@pytest.mark.parametrize("learn", [True, False])
def test_logvar_soft_bounds(learn: bool) -> None:
    ens = make(learn_logvar_bounds=learn)
    assert isinstance(ens.max_logvar, torch.nn.Parameter) == learn
    with torch.no_grad():
        ens.biases[-1][..., OUT:] = 0.0
        ens.weights[-1][..., OUT:] *= 1e4  # raw log-variances far outside the bounds, both signs
    x = torch.randn(E, 256, IN) * 1e3
    _, lv = ens(x)
    assert torch.isfinite(lv).all()
    raw = torch.cat([torch.full((1,), 1e6), torch.full((1,), -1e6), torch.linspace(-30, 30, 101)])
    bounded = ens.bound_logvar(raw[:, None].expand(-1, OUT))
    for out in (lv, bounded):
        # The double softplus exceeds max by softplus(-(max - min)) = 2.8e-5 at most.
        assert out.max() <= 0.5 + 3e-5
        assert out.min() >= -10.0
    assert lv.max() > 0.4 and lv.min() < -9.9  # the extremes really reach both bounds
    # Inside the bounds the map is close to the identity.
    mid = ens.bound_logvar(torch.full((OUT,), -4.0))
    torch.testing.assert_close(mid, torch.full((OUT,), -4.0), atol=0.02, rtol=0)


def test_normaliser_mean_std_constant_column_and_state_dict() -> None:
    ens = make()
    x = torch.randn(500, IN) * torch.tensor([1.0, 10.0, 0.1, 1.0, 1.0]) + torch.tensor([0.0, 5.0, -3.0, 2.0, 0.0])
    x[:, 3] = 2.0  # constant column
    x[:, 4] = 1e-7 * torch.randn(500)  # essentially constant column
    ens.fit_normaliser(x)
    torch.testing.assert_close(ens.input_mean, x.mean(0), atol=1e-5, rtol=1e-5)
    expected_std = x.double().std(0, correction=0).float()
    torch.testing.assert_close(ens.input_std[:3], expected_std[:3], rtol=1e-5, atol=0)
    assert ens.input_std[3] == 1.0 and ens.input_std[4] == 1.0
    z = ens.normalise(x)
    assert torch.isfinite(z).all()
    torch.testing.assert_close(z[:, :3].mean(0), torch.zeros(3), atol=1e-4, rtol=0)
    torch.testing.assert_close(z[:, :3].std(0, correction=0), torch.ones(3), atol=1e-4, rtol=0)
    assert torch.all(z[:, 3] == 0)
    mean, lv = ens(x)
    assert torch.isfinite(mean).all() and torch.isfinite(lv).all()
    # A single sample: std 0 everywhere -> 1, no nan.
    ens1 = make()
    ens1.fit_normaliser(x[:1])
    assert torch.all(ens1.input_std == 1.0)
    with pytest.raises(ValueError, match="non-finite"):
        ens1.fit_normaliser(torch.full((3, IN), float("nan")))

    # The normaliser and the elites travel with the state dict (elites of another length included).
    ens.set_elites(torch.tensor([2, 0]))
    sd = ens.state_dict()
    assert {"input_mean", "input_std", "elites", "max_logvar", "min_logvar"} <= set(sd)
    fresh = GaussianEnsemble(IN, OUT, ensemble_size=E, hidden_size=32)
    fresh.load_state_dict(sd)
    assert torch.equal(fresh.elites, torch.tensor([2, 0]))
    torch.testing.assert_close(fresh(x)[0], mean)
    with pytest.raises(ValueError, match="elites"):
        ens.set_elites(torch.tensor([0, E]))


def test_nll_matches_torch_gaussian_nll_loss() -> None:
    ens = make()
    x = torch.randn(E, 64, IN)
    target = torch.randn(E, 64, OUT)
    mean, lv = ens(x)
    ours = gaussian_nll(mean, lv, target)  # (E,), no constant
    ref = F.gaussian_nll_loss(mean, target, lv.exp(), full=False, reduction="none", eps=1e-12)
    torch.testing.assert_close(ours, ref.flatten(1).mean(1), rtol=1e-5, atol=1e-6)
    # Hand formula on a known case: mean 0, var e^1 = e, target 1 -> 0.5 * (1/e + 1).
    one = gaussian_nll(torch.zeros(1, 1, 1), torch.ones(1, 1, 1), torch.ones(1, 1, 1))
    torch.testing.assert_close(one, torch.tensor([0.5 * (math.exp(-1) + 1)]))


def test_gradients_flow_to_all_parameters() -> None:
    ens = make()
    x = torch.randn(E, 32, IN)
    mean, lv = ens(x)
    loss = (
        gaussian_nll(mean, lv, torch.randn(E, 32, OUT)).sum()
        + ens.weight_decay_loss()
        + 0.01 * ens.logvar_bound_penalty()
    )
    loss.backward()
    for name, p in ens.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name
    # Member-wise: member 1's loss reaches only member 1's weights.
    ens.zero_grad()
    mean, lv = ens(x)
    gaussian_nll(mean, lv, torch.zeros(E, 32, OUT))[1].backward()
    for w in ens.weights:
        assert w.grad[1].abs().sum() > 0
        assert torch.count_nonzero(w.grad[[0, 2, 3]]) == 0


def test_weight_decay_loss_formula() -> None:
    ens = make()
    expected = sum(d * 0.5 * (w.detach() ** 2).sum() for d, w in zip([2.5e-5, 5e-5, 7.5e-5, 7.5e-5, 1e-4], ens.weights))
    torch.testing.assert_close(ens.weight_decay_loss().detach(), expected)
    small = GaussianEnsemble(IN, OUT, ensemble_size=2, hidden_size=8, num_layers=1)
    assert small.decays == [2.5e-5, 1e-4]


@pytest.mark.parametrize("kind", ["gaussian", "deterministic"])
@pytest.mark.parametrize("shared", [False, True])
def test_inference_pads_an_odd_output_width_and_changes_no_value(monkeypatch, kind: str, shared: bool) -> None:
    """Without autograd the output layer (2 x 107 = 214 wide: the GEM head on Ant) runs padded to 216 columns;
    the outputs equal the unpadded (autograd) forward: bit for bit with MKL on the machine tested, and within
    float32 rounding anywhere."""
    from dynamics import networks as ensemble_module
    from dynamics.networks import DeterministicEnsemble

    torch.manual_seed(1)
    in_dim, out_dim, hidden = 30, 107, 64
    if kind == "gaussian":
        ens = GaussianEnsemble(in_dim, out_dim, ensemble_size=3, hidden_size=hidden, num_layers=2)
    else:
        ens = DeterministicEnsemble(in_dim, out_dim, ensemble_size=3, hidden_size=hidden, num_layers=2)
    x = torch.randn(50, in_dim) if shared else torch.randn(3, 50, in_dim)
    with torch.enable_grad():
        mean_ref, logvar_ref = ens(x)

    widths = []
    real_pad = F.pad

    def spy_pad(t, pad, *args, **kwargs):
        widths.append(t.shape[-1] + pad[1])
        return real_pad(t, pad, *args, **kwargs)

    monkeypatch.setattr(ensemble_module.F, "pad", spy_pad)
    with torch.no_grad():
        mean, logvar = ens(x)
    out_width = 2 * out_dim if kind == "gaussian" else out_dim
    assert widths == [out_width + (-out_width % 8)] * 2  # weight and bias of the output layer only
    assert mean.shape == mean_ref.shape == (3, 50, out_dim) and logvar.shape == logvar_ref.shape
    torch.testing.assert_close(mean, mean_ref.detach(), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(logvar, logvar_ref.detach(), rtol=1e-6, atol=1e-6)


def test_fused_path_is_on_exactly_where_onednn_runs_the_bf16_linear(monkeypatch) -> None:
    """The fused path is used where oneDNN itself runs a bf16 linear + SiLU on this CPU, and nowhere else: on an
    AVX2-only x86 CPU the op raises ("could not create a primitive descriptor"), and a bf16 planning step must
    then take autocast's batched path instead of crashing (found on an AMD EPYC Zen 3)."""
    from dynamics import fused

    x, w, b = torch.randn(8, 6).bfloat16(), torch.randn(4, 6).bfloat16(), torch.randn(4).bfloat16()
    try:
        out = torch.ops.mkldnn._linear_pointwise(x, w, b, "swish", [], "")
        expected = F.silu(x.float() @ w.float().T + b.float())
        onednn_runs = bool(torch.allclose(out.float(), expected, rtol=2e-2, atol=2e-2))
    except (RuntimeError, AttributeError):
        onednn_runs = False
    assert fused._AVAILABLE is onednn_runs

    monkeypatch.setattr(fused, "_AVAILABLE", False)  # as on such a CPU: bf16 inference still runs, batched
    monkeypatch.setattr(fused, "MIN_ROWS", 0)
    ens = GaussianEnsemble(6, 3, ensemble_size=2, hidden_size=16, num_layers=2)
    with torch.no_grad(), torch.autocast("cpu", torch.bfloat16):
        assert not fused.applies(torch.randn(2, 8, 6))
        mean, logvar = ens(torch.randn(2, 8, 6))
    assert mean.shape == (2, 8, 3) and torch.isfinite(mean).all() and torch.isfinite(logvar).all()


@pytest.mark.parametrize("shared,activation", [(False, "silu"), (True, "silu"), (False, "relu")])
def test_fused_cpu_bf16_path_matches_torch_ops_and_follows_weight_updates(monkeypatch, shared, activation) -> None:
    """Issue 13: under CPU bf16 autocast without autograd, with enough rows per member, each member runs as
    oneDNN fused linear + activation (SiLU, or ReLU) calls. Its outputs equal torch's own per-member ops in bf16
    (F.linear, F.silu / F.relu)
    to bf16 rounding, are as close to float32 as autocast's batched path, and follow in-place weight changes
    (the bf16 weight cache is keyed on the parameters' versions) and another member selection."""
    from dynamics import fused

    if not fused._AVAILABLE:
        pytest.skip("oneDNN has no fused bf16 linear on this CPU or build (AVX2-only x86: the batched bf16 path runs)")
    torch.manual_seed(3)
    ens = GaussianEnsemble(24, 18, ensemble_size=5, hidden_size=64, num_layers=3, activation=activation)
    idx = torch.tensor([4, 0, 2])
    rows = fused.MIN_ROWS
    x = torch.randn(rows, 24) if shared else torch.randn(3, rows, 24)
    calls = []
    real = fused.fused_member_mlp
    monkeypatch.setattr(fused, "fused_member_mlp", lambda *a: calls.append(1) or real(*a))

    def run(on: bool) -> tuple[torch.Tensor, torch.Tensor]:
        monkeypatch.setattr(fused, "FUSED_CPU_BF16", on)
        with torch.no_grad(), torch.autocast("cpu", torch.bfloat16):
            return ens(x, idx)

    with torch.no_grad():
        mean32, lv32 = ens(x, idx)
    (mean_f, lv_f), (mean_b, lv_b) = run(True), run(False)
    assert len(calls) == 1 and mean_f.dtype == torch.float32
    # torch's own ops per member, in bf16
    h = ens.normalise(x).to(torch.bfloat16)
    ref = []
    for j, k in enumerate(idx.tolist()):
        y = h if shared else h[j]
        for i, (w, b) in enumerate(zip(ens.weights, ens.biases)):
            y = F.linear(y, w[k].T.to(torch.bfloat16), b[k, 0].to(torch.bfloat16))
            y = getattr(F, activation)(y) if i < len(ens.weights) - 1 else y
        ref.append(y)
    with torch.no_grad():
        ref_mean = ens.denormalise_target(torch.stack(ref)[..., :18].float())
    scale = mean32.abs().max()
    assert (mean_f - ref_mean).abs().max() < 0.02 * scale  # bf16 rounding of a 4-layer chain
    err_f, err_b = (mean_f - mean32).abs().mean(), (mean_b - mean32).abs().mean()
    assert err_f < 1.2 * err_b and (lv_f - lv32).abs().mean() < 1.2 * (lv_b - lv32).abs().mean()
    if activation == "silu":  # really another kernel (len(calls) says so too); ReLU commutes with the bf16
        assert not torch.equal(mean_f, mean_b)  # rounding, so there both paths give the same bits
    # inside a cached_weights() scope (the evaluator opens one per call) the bf16 weights are prepared once per
    # selection; an in-place update of the weights (an optimiser step) and another selection are still seen
    with fused.cached_weights():
        assert torch.equal(run(True)[0], mean_f) and torch.equal(run(True)[0], mean_f)
        assert len(fused._SCOPE.cache) == 1
        with torch.no_grad():
            ens.weights[-1].mul_(2.0)
            mean32_new, _ = ens(x, idx)  # (the fp32 batched path caches its own prepared weights)
        mean_new, _ = run(True)
        assert sum(key[0] != "batched" for key in fused._SCOPE.cache) == 2
    assert fused._SCOPE.cache is None
    # (a stale cache would be off by the whole change)
    assert (mean_new - mean32_new).abs().mean() < 0.05 * (mean32_new - mean32).abs().mean()
    idx = torch.tensor([1, 3, 0])
    with torch.no_grad():
        mean32_other, _ = ens(x, idx)
    assert (run(True)[0] - mean32_other).abs().mean() < 0.05 * (mean32_other - mean32_new).abs().mean()
    # not with autograd, not below MIN_ROWS
    calls.clear()
    with torch.autocast("cpu", torch.bfloat16):
        ens(x, idx)
        with torch.no_grad():
            ens(x[..., : rows - 1, :], idx)
    assert calls == []


@pytest.mark.parametrize("bf16", [False, True])
def test_batched_weights_prepared_once_per_scope_give_the_same_bits_and_follow_updates(monkeypatch, bf16) -> None:
    """Inside a cached_weights() scope (one per evaluator call) the batched path selects, pads and casts the member
    weights once instead of on every forward (the fast preset's small GEMMs spent ~20 % of a step there): the
    outputs are bit for bit those of the per-forward preparation, and an in-place weight update is still seen."""
    from dynamics import fused

    monkeypatch.setattr(fused, "FUSED_CPU_BF16", False)  # the batched path at any row count
    torch.manual_seed(4)
    ens = GaussianEnsemble(24, 107, ensemble_size=5, hidden_size=64, num_layers=3)  # 214-wide output: padded
    x, idx = torch.randn(3, 40, 24), torch.tensor([4, 0, 2])

    def forward():
        with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=bf16):
            return ens(x, idx)

    before = forward()
    with fused.cached_weights():
        inside = forward(), forward()
        assert len(fused._SCOPE.cache) == 1  # prepared once for both forwards
        with torch.no_grad():
            ens.weights[1].mul_(1.5)
        updated = forward()
        assert len(fused._SCOPE.cache) == 2
    for got in inside:
        assert torch.equal(got[0], before[0]) and torch.equal(got[1], before[1])
    assert torch.equal(updated[0], forward()[0]) and not torch.equal(updated[0], before[0])


@pytest.mark.parametrize("kind", ["gaussian", "deterministic", "two-stage"])
def test_the_activation_is_the_one_asked_for_in_every_network(kind: str) -> None:
    """model.activation: every member network runs its hidden layers through it, checked against torch's own
    per-member ops (F.linear, then F.silu or F.relu); the default is SiLU (PETS', the GEM paper's); an unknown
    name is a ValueError naming the accepted ones."""
    from dynamics.networks import ACTIVATIONS, DeterministicEnsemble
    from gem_head.two_stage import TwoStageGemEnsemble
    from pets.config import _CHOICES

    assert tuple(ACTIVATIONS) == _CHOICES["model.activation"]  # pets.config lists them without importing torch

    def build(activation=None):
        torch.manual_seed(0)
        kw = {} if activation is None else {"activation": activation}
        if kind == "gaussian":
            return GaussianEnsemble(6, 4, ensemble_size=3, hidden_size=16, num_layers=2, **kw)
        if kind == "deterministic":
            return DeterministicEnsemble(6, 4, ensemble_size=3, hidden_size=16, num_layers=2, **kw)
        return TwoStageGemEnsemble(6, 4, [0, 2], [1, 3], ensemble_size=3, hidden_size=16, num_layers=2, **kw)

    def reference(ens, x, act):  # the first stage / the plain MLP, member 1
        weights, biases = (ens.coef_weights, ens.coef_biases) if kind == "two-stage" else (ens.weights, ens.biases)
        y = ens.normalise(x)
        for i, (w, b) in enumerate(zip(weights, biases)):
            y = F.linear(y, w[1].T, b[1, 0])
            y = act(y) if i < len(weights) - 1 else y
        return y

    x = torch.randn(10, 6) * 3
    assert build().activation == "silu"
    with torch.no_grad():
        for name, act in (("silu", F.silu), ("relu", F.relu)):
            ens = build(name)
            (ens.coef_weights if kind == "two-stage" else ens.weights)[0].mul_(3)  # more units below zero
            if kind == "two-stage":
                got = ens.coefficient_net(ens.normalise(x), torch.tensor([1]))[0]
            else:
                got = ens(x, torch.tensor([1]))[0][0]
                got = (got - ens.target_mean) / ens.target_std
            want = reference(ens, x, act)[..., : got.shape[-1]]
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
            other = F.relu if act is F.silu else F.silu
            assert not torch.allclose(got, reference(ens, x, other)[..., : got.shape[-1]], atol=1e-3)
    with pytest.raises(ValueError, match="activation must be one of silu, relu, got 'tanh'"):
        build("tanh")
