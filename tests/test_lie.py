"""Tests of gem_head.lie against independent ground truth.

References nobody here wrote: torch.linalg.matrix_exp (closed-form exp), scipy.spatial.transform.Rotation
(quaternions, rotation vectors, axis-angle), torch.autograd.gradcheck (backward passes), and the group
axioms / identities (round trips, R^T R = I, det R = 1, |R1 - R2|_F = 2 sqrt(2) sin(theta/2)).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from gem_head import lie
from gem_head.lie import SE2, SE3, SO2, SO3, Rn

DTYPES = [torch.float32, torch.float64]
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
BATCHES = [(), (3,), (2, 4)]
MATRIX_GROUPS = [SO2, SO3, SE2, SE3]
ANGLES = {
    "0": 0.0,
    "1e-8": 1e-8,
    "1e-5": 1e-5,
    "3e-3": 3e-3,
    "random": None,
    "pi-1e-3": math.pi - 1e-3,
    "pi-1e-7": math.pi - 1e-7,
    "pi": math.pi,
}
# Absolute/relative tolerance per dtype; entries involved are O(1)..O(pi).
TOL = {torch.float32: 1e-5, torch.float64: 1e-10}
HYP = settings(max_examples=50, deadline=None)


def gid(g) -> str:
    return g.__name__


def dname(d: torch.dtype) -> str:
    return str(d).replace("torch.", "")


def rot_slice(group) -> slice:
    """Which tangent entries are the rotation part."""
    return {SO2: slice(0, 1), SE2: slice(0, 1), SO3: slice(0, 3), SE3: slice(0, 3)}[group]


def make_tangent(group, angle: float | None, batch: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    """float64 tangent vectors whose rotation part has norm `angle` (random in [0.1, 3.0] when None),
    random axes / signs, and N(0, 1) translations."""
    g = torch.Generator().manual_seed(seed)
    if angle is None:
        ang = 0.1 + 2.9 * torch.rand(batch, generator=g, dtype=torch.float64)
    else:
        ang = torch.full(batch, angle, dtype=torch.float64)
    if group in (SO2, SE2):
        sign = torch.where(torch.rand(batch, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0)
        rot = (sign * ang).unsqueeze(-1)
        n_trans = 2 if group is SE2 else 0
    else:
        axis = torch.randn(*batch, 3, generator=g, dtype=torch.float64)
        axis = axis / axis.norm(dim=-1, keepdim=True)
        rot = axis * ang.unsqueeze(-1)
        n_trans = 3 if group is SE3 else 0
    trans = torch.randn(*batch, n_trans, generator=g, dtype=torch.float64)
    return torch.cat([rot, trans], dim=-1)


def ambiguous(angle: float | None, dtype: torch.dtype) -> bool:
    """At pi the log is two-valued. In float32, pi - 1e-7 rounds to a float whose exp lies within
    rounding of the angle-pi rotation, so the returned branch is not determined either."""
    if angle is None:
        return False
    return angle == math.pi or (dtype == torch.float32 and angle > math.pi - 1e-6)


def assert_rot_equal_mod_2pi(group, got: torch.Tensor, want: torch.Tensor, tol: float) -> None:
    """Rotation parts of two tangent vectors agree modulo 2 pi (on the rotation axis)."""
    s = rot_slice(group)
    a, b = got[..., s].double(), want[..., s].double()
    if a.shape[-1] == 1:
        d = a - b
        err = torch.atan2(torch.sin(d), torch.cos(d)).abs().squeeze(-1)
    else:
        th = b.norm(dim=-1, keepdim=True)
        alt = b - 2 * math.pi * b / th.clamp_min(1e-300)
        err = torch.minimum((a - b).norm(dim=-1), (a - alt).norm(dim=-1))
    assert err.max().item() <= tol, f"rotation parts differ modulo 2 pi by {err.max().item():.3g}"


def close(got: torch.Tensor, want: torch.Tensor, tol: float, msg: str = "") -> None:
    torch.testing.assert_close(got.double(), want.double(), atol=tol, rtol=tol, msg=lambda m: f"{msg}\n{m}")


# ----------------------------------------------------------------------------------------
# hat / vee, exp vs matrix_exp, round trips
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_hat_vee_inverse(group, dtype, batch, device):
    v = make_tangent(group, None, batch).to(dtype=dtype, device=device)
    m = group.hat(v)
    assert m.shape == (*batch, group.matrix_size, group.matrix_size)
    assert m.dtype == dtype and m.device.type == device
    assert torch.equal(group.vee(m), v)
    assert torch.equal(group.hat(group.vee(m)), m)
    # hat is linear in the basis E_i: hat(v) = sum_i v_i E_i with E_i = hat(e_i)
    basis = group.hat(torch.eye(group.dim, dtype=dtype, device=device))
    close(torch.einsum("...i,ijk->...jk", v, basis), m, TOL[dtype])


def test_basis_is_the_papers():
    """so(3) / se(3) generators E1..E6 of the paper (rotation first), so(2) = [[0, -1], [1, 0]]."""
    e1 = torch.tensor([[0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64)
    e2 = torch.tensor([[0, 0, 1], [0, 0, 0], [-1, 0, 0]], dtype=torch.float64)
    e3 = torch.tensor([[0, -1, 0], [1, 0, 0], [0, 0, 0]], dtype=torch.float64)
    eye = torch.eye(6, dtype=torch.float64)
    for i, e in enumerate([e1, e2, e3]):
        assert torch.equal(SO3.hat(eye[i, :3]), e)
        assert torch.equal(SE3.hat(eye[i])[:3, :3], e) and not SE3.hat(eye[i])[:, 3].any()
    for i in range(3):
        t = SE3.hat(eye[3 + i])
        assert t[i, 3] == 1 and t.abs().sum() == 1
    assert torch.equal(
        SO2.hat(torch.ones(1, dtype=torch.float64)), torch.tensor([[0.0, -1.0], [1.0, 0.0]], dtype=torch.float64)
    )
    assert torch.equal(SE2.hat(torch.tensor([1.0, 2.0, 3.0])), torch.tensor([[0.0, -1, 2], [1, 0, 3], [0, 0, 0]]))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("angle", list(ANGLES.values()), ids=list(ANGLES))
@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_exp_matches_matrix_exp(group, dtype, angle, batch, device):
    v64 = make_tangent(group, angle, batch).to(device)
    want = torch.linalg.matrix_exp(group.hat(v64))
    got = group.exp(v64.to(dtype))
    assert got.dtype == dtype and got.shape == want.shape
    close(got, want, TOL[dtype], f"{group.__name__}.exp vs matrix_exp")


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("angle", list(ANGLES.values()), ids=list(ANGLES))
@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_log_exp_round_trips(group, dtype, angle, batch, device):
    tol = TOL[dtype]
    v = make_tangent(group, angle, batch).to(dtype=dtype, device=device)
    x = group.exp(v)
    lg = group.log(x)
    assert lg.shape == v.shape and lg.dtype == dtype
    # exp(log X) = X holds everywhere, pi included.
    close(group.exp(lg), x, tol, "exp(log X) != X")
    if ambiguous(angle, dtype):
        assert_rot_equal_mod_2pi(group, lg, v, tol)
        assert lg[..., rot_slice(group)].norm(dim=-1).max() <= math.pi + tol
    else:
        close(lg, v, tol, "log(exp v) != v")


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("angle", list(ANGLES.values()), ids=list(ANGLES))
@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_group_axioms(group, dtype, angle, batch, device):
    tol = TOL[dtype]
    x = group.exp(make_tangent(group, angle, batch, seed=1).to(dtype=dtype, device=device))
    y = group.exp(make_tangent(group, None, batch, seed=2).to(dtype=dtype, device=device))
    z = group.exp(make_tangent(group, angle, batch, seed=3).to(dtype=dtype, device=device))
    eye = group.identity(batch, dtype=dtype, device=device)
    close(group.compose(x, group.inverse(x)), eye, tol, "X X^-1 != I")
    close(group.compose(group.inverse(x), x), eye, tol, "X^-1 X != I")
    close(group.compose(group.compose(x, y), z), group.compose(x, group.compose(y, z)), tol, "not associative")
    close(group.inverse(group.compose(x, y)), group.compose(group.inverse(y), group.inverse(x)), tol)
    assert torch.equal(group.compose(eye, x), x)
    # on the manifold: R^T R = I, det R = 1, homogeneous bottom row exact
    n = 3 if group in (SO3, SE3) else 2
    r = x[..., :n, :n]
    close(r.transpose(-1, -2) @ r, torch.eye(n, dtype=dtype, device=device).expand_as(r), tol)
    close(torch.linalg.det(r.double()), torch.ones(batch, dtype=torch.float64, device=device), tol)
    if group in (SE2, SE3):
        bottom = torch.zeros(group.matrix_size, dtype=dtype, device=device)
        bottom[-1] = 1
        assert torch.equal(x[..., -1, :], bottom.expand_as(x[..., -1, :]))
        assert torch.equal(group.inverse(x)[..., -1, :], bottom.expand_as(x[..., -1, :]))


@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_one_parameter_subgroup(group, dtype):
    """exp(s v) exp(t v) = exp((s + t) v)."""
    v = make_tangent(group, 1.0, (5,))
    s, t = 0.3, 1.4
    got = group.compose(group.exp((s * v).to(dtype)), group.exp((t * v).to(dtype)))
    close(got, torch.linalg.matrix_exp(group.hat((s + t) * v)), TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_threshold_continuity(group, dtype):
    """Just below / above the small-angle threshold, exp matches matrix_exp and its Jacobian is continuous."""
    thr = lie.small_angle_threshold(dtype)
    jacs = []
    for f in (1 - 1e-4, 1 + 1e-4):
        v64 = make_tangent(group, thr * f, (), seed=4)
        close(group.exp(v64.to(dtype)), torch.linalg.matrix_exp(group.hat(v64)), TOL[dtype])
        jacs.append(torch.autograd.functional.jacobian(group.exp, v64.to(dtype)).double())
        close(group.log(group.exp(v64.to(dtype))), v64, TOL[dtype])
    # the two points differ by 2e-4 * thr in angle and the second derivative of exp is O(1): no jump allowed
    close(jacs[0], jacs[1], 10 * TOL[dtype] + 1e-3 * thr)


# ----------------------------------------------------------------------------------------
# gradients
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "angle", [0.0, 1e-8, math.pi - 1e-3, math.pi - 1e-7, math.pi], ids=["0", "1e-8", "pi-1e-3", "pi-1e-7", "pi"]
)
@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_gradients_finite_and_nonzero(group, dtype, angle, device):
    v = make_tangent(group, angle, (4,), seed=5).to(dtype=dtype, device=device).requires_grad_(True)
    w_exp = torch.randn(4, group.matrix_size, group.matrix_size, dtype=dtype, device=device)
    (group.exp(v) * w_exp).sum().backward()
    assert torch.isfinite(v.grad).all(), f"exp grad not finite: {v.grad}"
    assert (v.grad.abs().sum(-1) > 0).all(), "exp grad vanished"

    x = group.exp(v.detach()).requires_grad_(True)
    w_log = torch.randn(4, group.dim, dtype=dtype, device=device)
    (group.log(x) * w_log).sum().backward()
    assert torch.isfinite(x.grad).all(), f"log grad not finite: {x.grad}"
    assert (x.grad.abs().flatten(1).sum(-1) > 0).all(), "log grad vanished"


@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_differentials_at_identity(group, dtype):
    """d exp at 0 maps e_i to the generator E_i; d log at I maps E_i back to e_i (exact, no NaN at 0)."""
    eye_t = torch.eye(group.dim, dtype=dtype)
    jac = torch.autograd.functional.jacobian(group.exp, torch.zeros(group.dim, dtype=dtype))
    close(jac.movedim(-1, 0), group.hat(eye_t), TOL[dtype])
    jl = torch.autograd.functional.jacobian(group.log, group.identity(dtype=dtype))  # (dim, n, n)
    close(torch.einsum("ajk,bjk->ba", jl, group.hat(eye_t)), eye_t, TOL[dtype])


@pytest.mark.parametrize(
    "angle",
    [a for a in ANGLES.values() if a != math.pi] + [0.0999, 0.1001],
    ids=[k for k in ANGLES if k != "pi"] + ["thr32-", "thr32+"],
)
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_float32_jacobians_match_float64(group, angle):
    """No cancellation blow-up in float32 derivatives (Taylor vs closed-form branches, near pi, at 0)."""
    jac = torch.autograd.functional.jacobian
    v = make_tangent(group, angle, (), seed=3)
    x = group.exp(v)
    close(jac(group.exp, v.float()), jac(group.exp, v), TOL[torch.float32])
    close(jac(group.log, x.float()), jac(group.log, x), TOL[torch.float32])


@pytest.mark.parametrize("angle", [1e-3, 0.05, 1.7, math.pi - 0.05], ids=["1e-3", "0.05", "1.7", "pi-0.05"])
@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_gradcheck(group, angle):
    """float64 gradcheck of exp (w.r.t. the tangent vector) and log (w.r.t. all matrix entries)."""
    v = make_tangent(group, angle, (2,), seed=6).requires_grad_(True)
    assert torch.autograd.gradcheck(group.exp, (v,))
    x = group.exp(v.detach()).requires_grad_(True)
    assert torch.autograd.gradcheck(group.log, (x,))


def test_gradcheck_quaternions():
    g = torch.Generator().manual_seed(7)
    q = torch.randn(3, 4, generator=g, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(SO3.from_quat, (q,))
    assert torch.autograd.gradcheck(SO3.quat_log, (q,))
    r = SO3.from_quat(q.detach()).requires_grad_(True)
    assert torch.autograd.gradcheck(SO3.to_quat, (r,))
    v = torch.randn(3, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(SO3.quat_exp, (v,))


# ----------------------------------------------------------------------------------------
# SO(3) conversions against scipy
# ----------------------------------------------------------------------------------------


def _scipy_quat(rot: Rotation) -> torch.Tensor:
    """scipy's (x, y, z, w) -> (w, x, y, z), canonical w >= 0."""
    xyzw = rot.as_quat(canonical=True)
    return torch.from_numpy(np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1))


def _assert_quat_close(got: torch.Tensor, want: torch.Tensor, tol: float, w_nonneg: bool = True) -> None:
    """Quaternions equal up to the overall sign (only ambiguous when w ~ 0); to_quat promises w >= 0."""
    got, want = got.double(), want.double()
    err = torch.minimum((got - want).norm(dim=-1), (got + want).norm(dim=-1))
    assert err.max() <= tol, err.max()
    if w_nonneg:
        assert (got[..., 0] >= 0).all()


@pytest.mark.parametrize("angle", list(ANGLES.values()), ids=list(ANGLES))
@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
def test_so3_against_scipy(dtype, angle):
    tol = TOL[dtype]
    v = make_tangent(SO3, angle, (7,), seed=8)
    ref = Rotation.from_rotvec(v.numpy())
    r_ref = torch.from_numpy(ref.as_matrix())
    x = v.to(dtype)
    close(SO3.exp(x), r_ref, tol, "exp vs from_rotvec")
    axis = (
        v / v.norm(dim=-1, keepdim=True).clamp_min(1e-300) if angle != 0.0 else torch.tensor([[0.0, 0, 1]]).expand(7, 3)
    )
    ang = v.norm(dim=-1)
    close(SO3.from_axis_angle((3.0 * axis).to(dtype), ang.to(dtype)), r_ref, tol, "from_axis_angle")
    _assert_quat_close(SO3.to_quat(r_ref.to(dtype)), _scipy_quat(ref), tol)
    # quat_exp is (cos(t/2), sin(t/2) u): at t = pi its w is +-rounding, so no sign promise there
    _assert_quat_close(SO3.quat_exp(x), _scipy_quat(ref), tol, w_nonneg=False)
    close(SO3.from_quat(_scipy_quat(ref).to(dtype)), r_ref, tol, "from_quat")
    rotvec = torch.from_numpy(Rotation.from_matrix(r_ref.numpy()).as_rotvec())
    for name, got in (("log", SO3.log(r_ref.to(dtype))), ("quat_log", SO3.quat_log(_scipy_quat(ref).to(dtype)))):
        if ambiguous(angle, dtype):
            assert_rot_equal_mod_2pi(SO3, got, rotvec, tol)
        else:
            close(got, rotvec, tol, name)
    close(SO3.angle(r_ref.to(dtype)), torch.from_numpy(ref.magnitude()), tol)


@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
def test_quaternion_conversions_random(dtype):
    """Unnormalised random quaternions: from_quat normalises; to_quat returns the unit w >= 0 one; quat_mul."""
    g = torch.Generator().manual_seed(9)
    q = torch.randn(64, 4, generator=g, dtype=torch.float64) * 3
    p = torch.randn(64, 4, generator=g, dtype=torch.float64)
    xyzw = lambda t: np.concatenate([t[..., 1:].numpy(), t[..., :1].numpy()], axis=-1)  # noqa: E731
    rq, rp = Rotation.from_quat(xyzw(q)), Rotation.from_quat(xyzw(p))
    close(SO3.from_quat(q.to(dtype)), torch.from_numpy(rq.as_matrix()), TOL[dtype])
    _assert_quat_close(SO3.to_quat(SO3.from_quat(q.to(dtype))), _scipy_quat(rq), TOL[dtype])
    pq = SO3.quat_mul(p.to(dtype), q.to(dtype))
    close(SO3.from_quat(pq), torch.from_numpy((rp * rq).as_matrix()), TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
def test_so3_log_exactly_pi_axis_aligned(dtype):
    """Rotations by exactly pi about the axes and a diagonal: R + R^T is singular, trace = -1."""
    axes = torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 1]], dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    r = 2 * axes.unsqueeze(-1) * axes.unsqueeze(-2) - torch.eye(3, dtype=torch.float64)  # exact pi rotations
    lg = SO3.log(r.to(dtype))
    assert_rot_equal_mod_2pi(SO3, lg, math.pi * axes, TOL[dtype])
    close(SO3.exp(lg), r, TOL[dtype])
    close(lg.norm(dim=-1), torch.full((5,), math.pi, dtype=torch.float64), TOL[dtype])


def test_frobenius_angle_identity():
    """|R1 - R2|_F = 2 sqrt(2) sin(theta / 2), theta the angle of R1^T R2 (SO(3); SO(2) too)."""
    for group, angle_of in ((SO3, SO3.angle), (SO2, lambda r: SO2.to_angle(r).abs())):
        a = group.exp(make_tangent(group, None, (50,), seed=10))
        b = group.exp(make_tangent(group, None, (50,), seed=11))
        theta = angle_of(group.compose(group.inverse(a), b))
        close(torch.linalg.matrix_norm(a - b), 2 * math.sqrt(2) * torch.sin(theta / 2), 1e-12)


# ----------------------------------------------------------------------------------------
# SO(2) conversions, SE from_rt / to_rt, R^n
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
def test_so2_conversions(dtype, batch):
    tol = TOL[dtype]
    g = torch.Generator().manual_seed(12)
    theta = (torch.rand(batch, generator=g, dtype=torch.float64) * 20 - 10).to(dtype)  # beyond +-pi on purpose
    r = SO2.from_angle(theta)
    assert r.shape == (*batch, 2, 2)
    assert torch.equal(r, SO2.exp(theta.unsqueeze(-1)))
    close(SO2.from_cos_sin(torch.cos(theta), torch.sin(theta)), r, tol)
    close(SO2.from_cos_sin(3 * torch.cos(theta), 3 * torch.sin(theta), normalize=True), r, tol)
    back = SO2.to_angle(r)
    assert back.shape == batch and (back.abs() <= math.pi + tol).all()
    d = (back - theta).double()
    close(torch.atan2(torch.sin(d), torch.cos(d)), torch.zeros_like(d), 10 * tol)  # theta up to 10: 10 ulp-scale
    close(SO2.log(r).squeeze(-1), back, 0.0)


WRAP_CASES = [0.0, 1e-9, -1e-9, 0.5, -0.5, 3.0, -3.0, math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 5 * math.pi]
WRAP_CASES += [2 * math.pi, -2 * math.pi, 4.0, -7.5, 100.0, -1000.5, 12345.678, 1e6, -1e6 - 0.25, 3e7 + 0.5]


@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
def test_wrap_angle_against_remainder(dtype):
    """lie.wrap_angle (= SO2.wrap) is math.remainder(d, 2 pi) with the tie -pi sent to +pi: values in (-pi, pi]."""
    assert lie.wrap_angle is SO2.wrap
    d = torch.tensor(WRAP_CASES, dtype=dtype)
    got = lie.wrap_angle(d)
    assert got.dtype == dtype and got.shape == d.shape
    eps = torch.finfo(dtype).eps
    for x, w in zip(d.double().tolist(), got.double().tolist()):  # x: the angle as the dtype holds it
        tol = 8 * eps * max(1.0, abs(x))
        want = math.remainder(x, 2 * math.pi)  # exact, in [-pi, pi], ties to even
        if abs(abs(want) - math.pi) <= tol:  # an odd multiple of pi (up to the dtype's rounding): +pi
            assert abs(w - math.pi) <= tol, (x, w)
        else:
            assert abs(w - want) <= tol, (x, w, want)
    pi = torch.tensor([math.pi, -math.pi], dtype=dtype)  # the dtype's own +-pi map to +pi exactly
    assert torch.equal(lie.wrap_angle(pi), pi.abs())


@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
def test_wrap_angle_against_numpy(dtype):
    """Dense angles against np.angle(exp(i d)) (away from odd multiples of pi); |d| < pi is returned unchanged."""
    d = torch.linspace(-50, 50, 10001, dtype=torch.float64).to(dtype)
    got = lie.wrap_angle(d)
    want = torch.from_numpy(np.angle(np.exp(1j * d.double().numpy())))
    close(got, want, 100 * torch.finfo(dtype).eps)
    assert (got > -math.pi).all() and (got <= math.pi).all()
    inside = d[d.abs() < math.pi]
    assert torch.equal(lie.wrap_angle(inside), inside)  # bitwise: no rounding inside the interval


@pytest.mark.parametrize("group", [SE2, SE3], ids=gid)
def test_se_from_rt_to_rt(group):
    n = 2 if group is SE2 else 3
    rgroup = SO2 if group is SE2 else SO3
    r = rgroup.exp(make_tangent(rgroup, None, (4,)))
    t = torch.randn(4, n, dtype=torch.float64)
    x = group.from_rt(r, t)
    r2, t2 = group.to_rt(x)
    assert torch.equal(r2, r) and torch.equal(t2, t)
    # the V-matrix: exp(0, u) is a pure translation by u
    assert torch.equal(
        group.to_rt(group.exp(torch.cat([torch.zeros(4, rgroup.dim, dtype=torch.float64), t], -1)))[1], t
    )


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("dtype", DTYPES, ids=dname)
def test_rn(dtype, batch, device):
    g = torch.Generator().manual_seed(13)
    a, b, c = (
        torch.randn(*batch, 4, generator=g, dtype=torch.float64).to(dtype=dtype, device=device) for _ in range(3)
    )
    assert Rn.dim is None and Rn(4).dim == 4 and repr(Rn(4)) == "Rn(4)"
    assert torch.equal(Rn.vee(Rn.hat(a)), a) and torch.equal(Rn.hat(Rn.vee(Rn.hat(a))), Rn.hat(a))
    assert torch.equal(Rn.exp(a), a) and torch.equal(Rn.log(a), a)
    assert torch.equal(Rn(4).exp(a), a)
    close(Rn.to_matrix(Rn.exp(a)), torch.linalg.matrix_exp(Rn.hat(a.double())), TOL[dtype])
    close(Rn.to_matrix(Rn.compose(a, b)), Rn.to_matrix(a) @ Rn.to_matrix(b), TOL[dtype])
    assert torch.equal(Rn.compose(a, Rn.inverse(a)), Rn.identity(batch, n=4, dtype=dtype, device=device))
    close(Rn.compose(Rn.compose(a, b), c), Rn.compose(a, Rn.compose(b, c)), TOL[dtype])


# ----------------------------------------------------------------------------------------
# the LieGroup protocol
# ----------------------------------------------------------------------------------------

PROTOCOL = ("exp", "log", "compose", "inverse", "hat", "vee", "identity")


def test_protocol_is_abstract():
    assert set(lie.LieGroup.__abstractmethods__) == set(PROTOCOL)
    with pytest.raises(TypeError, match="abstract"):
        lie.LieGroup()  # type: ignore[abstract]

    class Partial(lie.MatrixLieGroup):  # compose and identity come from MatrixLieGroup, the rest is missing
        dim, matrix_size = 1, 2

    assert set(Partial.__abstractmethods__) == set(PROTOCOL) - {"compose", "identity"}


@pytest.mark.parametrize("group", [*MATRIX_GROUPS, Rn], ids=gid)
def test_every_group_implements_the_protocol(group):
    assert issubclass(group, lie.LieGroup) and not group.__abstractmethods__
    assert issubclass(group, lie.MatrixLieGroup) == (group is not Rn)
    for name in PROTOCOL:
        assert callable(getattr(group, name)), name
        assert not getattr(getattr(group, name), "__isabstractmethod__", False), name
    if group is Rn:
        assert Rn.dim is None and Rn.matrix_size is None and Rn(4).matrix_size == 5
    else:
        assert isinstance(group.dim, int) and isinstance(group.matrix_size, int)


def _round_trip(group: type[lie.LieGroup], v: torch.Tensor, **identity_kw) -> None:
    """One pass through the base-class interface only: exp/log, compose/inverse/identity, hat/vee."""
    x = group.exp(v)
    close(group.exp(group.log(x)), x, 1e-12)
    close(group.log(x), v, 1e-12)
    close(group.compose(x, group.inverse(x)), group.identity(v.shape[:-1], dtype=v.dtype, **identity_kw), 1e-12)
    close(group.compose(group.inverse(x), x), group.identity(v.shape[:-1], dtype=v.dtype, **identity_kw), 1e-12)
    assert torch.equal(group.vee(group.hat(v)), v)


@pytest.mark.parametrize("group", [*MATRIX_GROUPS, Rn], ids=gid)
def test_protocol_round_trip(group):
    g = torch.Generator().manual_seed(21)
    if group is Rn:
        _round_trip(Rn, torch.randn(5, 4, generator=g, dtype=torch.float64), n=4)
    else:
        _round_trip(group, _clip_rotation(group, torch.randn(5, group.dim, generator=g, dtype=torch.float64)))


# ----------------------------------------------------------------------------------------
# input validation
# ----------------------------------------------------------------------------------------


def test_bad_inputs_raise_value_error():
    with pytest.raises(ValueError, match=r"SO3.exp expects a tensor of shape \(\.\.\., 3\)"):
        SO3.exp(torch.zeros(4, 2))
    with pytest.raises(ValueError, match=r"SE3.log expects a tensor of shape \(\.\.\., 4, 4\)"):
        SE3.log(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="floating-point"):
        SO2.exp(torch.zeros(3, 1, dtype=torch.long))
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        SO3.from_quat(torch.zeros(3))
    with pytest.raises(ValueError, match="SE2.hat"):
        SE2.hat(torch.zeros(2))
    with pytest.raises(ValueError, match="positive integer"):
        Rn(0)
    with pytest.raises(ValueError, match="Rn.vee"):
        Rn.vee(torch.zeros(3, 2))
    with pytest.raises(ValueError, match="torch.Tensor"):
        SO2.from_angle(1.0)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------
# property tests (hypothesis)
# ----------------------------------------------------------------------------------------


def _tangents(dim: int, batch: int = 3):
    return arrays(np.float64, (batch, dim), elements=st.floats(-3.0, 3.0, allow_nan=False, width=64))


def _clip_rotation(group, v: torch.Tensor, max_angle: float = math.pi - 1e-3) -> torch.Tensor:
    """Scale rotation parts into |angle| <= max_angle, where the log is single-valued."""
    s = rot_slice(group)
    rot = v[..., s]
    n = rot.norm(dim=-1, keepdim=True)
    scale = torch.where(n > max_angle, max_angle / n.clamp_min(1e-300), torch.ones_like(n))
    return torch.cat([rot * scale, v[..., s.stop :]], dim=-1)


@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_property_round_trips(group):
    @HYP
    @given(_tangents(group.dim), st.sampled_from(DTYPES))
    def check(arr, dtype):
        v = _clip_rotation(group, torch.from_numpy(arr))
        x = group.exp(v.to(dtype))
        close(x, torch.linalg.matrix_exp(group.hat(v)), TOL[dtype])
        close(group.log(x), v, TOL[dtype])
        close(group.exp(group.log(x)), x, TOL[dtype])
        assert torch.equal(group.vee(group.hat(v)), v)

    check()


@pytest.mark.parametrize("group", MATRIX_GROUPS, ids=gid)
def test_property_group_axioms(group):
    @HYP
    @given(_tangents(group.dim), _tangents(group.dim), _tangents(group.dim))
    def check(a, b, c):
        x, y, z = (group.exp(torch.from_numpy(t)) for t in (a, b, c))
        tol = 1e-10
        close(group.compose(group.compose(x, y), z), group.compose(x, group.compose(y, z)), tol)
        close(group.compose(x, group.inverse(x)), group.identity((3,), dtype=torch.float64), tol)
        xy = group.compose(x, y)
        close(group.exp(group.log(xy)), xy, tol)
        n = 3 if group in (SO3, SE3) else 2
        r = xy[..., :n, :n]
        close(r.transpose(-1, -2) @ r, torch.eye(n, dtype=torch.float64).expand_as(r), tol)
        close(torch.linalg.det(r), torch.ones(3, dtype=torch.float64), tol)

    check()


@HYP
@given(arrays(np.float64, (5, 4), elements=st.floats(-1.0, 1.0, allow_nan=False, width=64)))
def test_property_random_rotations(qarr):
    """Random (unnormalised) quaternions: on-manifold matrices that agree with scipy; round trips."""
    q = torch.from_numpy(qarr)
    q = q[q.norm(dim=-1) > 1e-2]
    if q.shape[0] == 0:
        return
    r = SO3.from_quat(q)
    close(r.transpose(-1, -2) @ r, torch.eye(3, dtype=torch.float64).expand_as(r), 1e-12)
    close(torch.linalg.det(r), torch.ones(q.shape[0], dtype=torch.float64), 1e-12)
    ref = Rotation.from_quat(np.concatenate([q[..., 1:].numpy(), q[..., :1].numpy()], -1))
    close(r, torch.from_numpy(ref.as_matrix()), 1e-12)
    _assert_quat_close(SO3.to_quat(r), _scipy_quat(ref), 1e-12)
    close(SO3.exp(SO3.log(r)), r, 1e-12)
    assert_rot_equal_mod_2pi(SO3, SO3.log(r), torch.from_numpy(ref.as_rotvec()), 1e-10)
