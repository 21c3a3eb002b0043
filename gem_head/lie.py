"""Batched, differentiable Lie-group kernels: SO(2), SO(3), SE(2), SE(3) and R^n.

Every function works on tensors with any leading (batch) dimensions, in float32 or
float64, on the device of its inputs, and is differentiable with finite gradients
everywhere on the group, including exactly at the identity (angle 0) and at angle pi.

Representations
  - SO(2): 2x2 rotation matrices; tangent vectors have shape (..., 1).
  - SO(3): 3x3 rotation matrices; tangent (..., 3) = (wx, wy, wz) in the paper's basis
    E1, E2, E3 (rotations about x, y, z): hat(w) = [[0, -wz, wy], [wz, 0, -wx], [-wy, wx, 0]].
  - SE(2): 3x3 homogeneous matrices [[R, t], [0, 1]]; tangent (..., 3) = (omega, vx, vy).
  - SE(3): 4x4 homogeneous matrices [[R, t], [0, 1]]; tangent (..., 6) = (wx, wy, wz, vx, vy, vz),
    rotation first as in the paper (E1..E3 rotations, E4..E6 translations).
  - R^n: group elements are plain vectors (..., n), tangent vectors too (any trailing n);
    exp/log are the identity and compose is addition. ``Rn.dim`` is ``None`` (any n);
    an instance ``Rn(n)`` carries ``dim == n`` for code that needs a number.

All exponentials and logarithms are closed forms (cos/sin, Rodrigues, V-matrices), never
``torch.linalg.matrix_exp``. Coefficients such as sin(theta)/theta are evaluated from
theta^2 with a Taylor polynomial (4 terms, truncation error far below the dtype's epsilon)
when theta is below a dtype-dependent threshold (theta < 0.1 in float32, theta < 1e-2 in
float64), and with the "double where" pattern: the closed-form branch sees
``theta2_safe = where(small, 1, theta2)``, so it never produces inf/NaN values or gradients
that the masked-out branch could leak into the backward pass.

The SO(3) logarithm goes through a unit quaternion obtained by Shepperd's method (the
largest of the four diagonal-based candidates is used, so every square root has an
argument >= 1) with w >= 0, then theta = 2 atan2(|xyz|, w). This is accurate at small
angles and at pi alike; at exactly pi the axis sign is arbitrary (both are valid logs).

Quaternions are (w, x, y, z), scalar first, as in MuJoCo observations.

Every group is a subclass of :class:`LieGroup` (the protocol: ``exp``, ``log``, ``compose``, ``inverse``, ``hat``,
``vee``, ``identity``, ``dim``, ``matrix_size``), used through the class itself (``SO3.exp(v)``), as in LieTorch /
PyPose; the matrix groups share ``compose`` (matrix product) and ``identity`` through :class:`MatrixLieGroup`.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["LieGroup", "MatrixLieGroup", "SO2", "SO3", "SE2", "SE3", "Rn", "small_angle_threshold", "wrap_angle"]


# ----------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------

_TWO_PI = 2.0 * math.pi

#: theta^2 below which Taylor polynomials replace the closed forms, per dtype.
_SMALL_SQ: dict[torch.dtype, float] = {torch.float64: 1e-4, torch.float32: 1e-2}
_SMALL_SQ_DEFAULT = 1e-1  # float16 / bfloat16


def small_angle_threshold(dtype: torch.dtype) -> float:
    """Angle (radians) below which the Taylor branches are used for ``dtype``."""
    return _SMALL_SQ.get(dtype, _SMALL_SQ_DEFAULT) ** 0.5


def _small_sq(dtype: torch.dtype) -> float:
    return _SMALL_SQ.get(dtype, _SMALL_SQ_DEFAULT)


def _check_float(x: Tensor, where: str) -> None:
    if not isinstance(x, Tensor):
        raise ValueError(f"{where} expects a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise ValueError(f"{where} expects a floating-point tensor (float32 or float64), got dtype {x.dtype}")


def _check_vec(x: Tensor, n: int | None, where: str) -> None:
    _check_float(x, where)
    if x.dim() < 1 or (n is not None and x.shape[-1] != n):
        want = f"(..., {n})" if n is not None else "(..., n) with at least one dimension"
        raise ValueError(f"{where} expects a tensor of shape {want}, got shape {tuple(x.shape)}")


def _check_mat(x: Tensor, n: int, where: str) -> None:
    _check_float(x, where)
    if x.dim() < 2 or x.shape[-2:] != (n, n):
        raise ValueError(f"{where} expects a tensor of shape (..., {n}, {n}), got shape {tuple(x.shape)}")


def _poly(t2: Tensor, coeffs: Sequence[float]) -> Tensor:
    """sum_k coeffs[k] * t2**k by Horner's rule."""
    out = torch.full_like(t2, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * t2 + c
    return out


def _safe(theta2: Tensor) -> tuple[Tensor, Tensor]:
    """(small mask, theta_safe): theta_safe = sqrt(where(small, 1, theta2)) (the double-where pattern)."""
    small = theta2 < _small_sq(theta2.dtype)
    return small, torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))


def _half_angle(theta2: Tensor) -> tuple[Tensor, Tensor]:
    """(cos(theta/2), sin(theta/2)/theta) from theta^2.

    Taylor: cos(theta/2) = 1 - t/8 + t^2/384 - t^3/46080, sin(theta/2)/theta = (1 - t/24 + t^2/1920 - t^3/322560)/2
    with t = theta^2.
    """
    small, th = _safe(theta2)
    h = 0.5 * th
    c = torch.where(small, _poly(theta2, (1.0, -1 / 8, 1 / 384, -1 / 46080)), torch.cos(h))
    k = torch.where(small, _poly(theta2, (0.5, -1 / 48, 1 / 3840, -1 / 645120)), torch.sin(h) / th)
    return c, k


def _coef_c(theta2: Tensor) -> Tensor:
    """(theta - sin theta)/theta^3; Taylor 1/6 - t/120 + t^2/5040 - t^3/362880 (t = theta^2)."""
    small, th = _safe(theta2)
    big = (th - torch.sin(th)) / (th * th * th)
    return torch.where(small, _poly(theta2, (1 / 6, -1 / 120, 1 / 5040, -1 / 362880)), big)


def _coef_xcotx(theta2: Tensor) -> Tensor:
    """(theta/2) cot(theta/2); Taylor 1 - t/12 - t^2/720 - t^3/30240 (t = theta^2). Valid for theta < 2 pi."""
    small, th = _safe(theta2)
    h = 0.5 * th
    big = h * torch.cos(h) / torch.sin(h)
    return torch.where(small, _poly(theta2, (1.0, -1 / 12, -1 / 720, -1 / 30240)), big)


def _coef_d(theta2: Tensor) -> Tensor:
    """(1 - (theta/2) cot(theta/2)) / theta^2; Taylor 1/12 + t/720 + t^2/30240 + t^3/1209600 (t = theta^2)."""
    small, th = _safe(theta2)
    h = 0.5 * th
    big = (1.0 - h * torch.cos(h) / torch.sin(h)) / (th * th)
    return torch.where(small, _poly(theta2, (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600)), big)


def _eye(n: int, like: Tensor) -> Tensor:
    return torch.eye(n, dtype=like.dtype, device=like.device)


def _identity(
    n: int, batch_shape: Sequence[int], dtype: torch.dtype | None, device: torch.device | str | None
) -> Tensor:
    eye = torch.eye(n, dtype=dtype if dtype is not None else torch.get_default_dtype(), device=device)
    return eye.expand(*batch_shape, n, n).clone()


def _homogeneous(r: Tensor, t: Tensor) -> Tensor:
    """[[R, t], [0, 1]] from R (..., n, n) and t (..., n), batch dims broadcast."""
    n = r.shape[-1]
    batch = torch.broadcast_shapes(r.shape[:-2], t.shape[:-1])
    r = r.expand(*batch, n, n)
    t = t.expand(*batch, n)
    top = torch.cat([r, t.unsqueeze(-1)], dim=-1)
    bottom = torch.zeros(*batch, 1, n + 1, dtype=r.dtype, device=r.device)
    bottom[..., 0, n] = 1.0
    return torch.cat([top, bottom], dim=-2)


# ----------------------------------------------------------------------------------------
# the group protocol
# ----------------------------------------------------------------------------------------


class LieGroup(ABC):
    """A Lie group as a namespace of batched closed forms; its subclasses are used as classes (``SO3.exp(v)``).

    Elements are tensors with any leading batch dims (matrices, or vectors for R^n); tangent vectors are
    (..., dim) coefficients in the group's basis. Every group implements the operations below, with
    exp(log(x)) = x, compose(x, inverse(x)) = identity and vee(hat(v)) = v.
    """

    #: Tangent (algebra) dimension; None where it is any n (R^n).
    dim: int | None
    #: Side of the square matrices ``hat`` returns; None where it depends on n (R^n: n + 1).
    matrix_size: int | None

    @staticmethod
    @abstractmethod
    def exp(v: Tensor) -> Tensor:
        """Exponential map: tangent (..., dim) -> group element."""

    @staticmethod
    @abstractmethod
    def log(x: Tensor) -> Tensor:
        """Logarithm, the inverse of ``exp`` on its principal branch: group element -> tangent (..., dim)."""

    @staticmethod
    @abstractmethod
    def compose(a: Tensor, b: Tensor) -> Tensor:
        """Group product a o b (batch dims broadcast)."""

    @staticmethod
    @abstractmethod
    def inverse(x: Tensor) -> Tensor:
        """Group inverse x^-1."""

    @staticmethod
    @abstractmethod
    def hat(v: Tensor) -> Tensor:
        """Tangent (..., dim) -> algebra matrix (..., matrix_size, matrix_size)."""

    @staticmethod
    @abstractmethod
    def vee(m: Tensor) -> Tensor:
        """Algebra matrix -> tangent (..., dim), the inverse of ``hat``."""

    @staticmethod
    @abstractmethod
    def identity(
        batch_shape: Sequence[int] = (), *, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> Tensor:
        """Identity elements of batch shape ``batch_shape`` (R^n also needs ``n=``)."""


class MatrixLieGroup(LieGroup):
    """A group of (matrix_size x matrix_size) matrices: the product is the matrix product, the identity is I."""

    dim: int
    matrix_size: int

    @classmethod
    def compose(cls, a: Tensor, b: Tensor) -> Tensor:
        """a o b = a @ b (batch dims broadcast)."""
        where = f"{cls.__name__}.compose"
        _check_mat(a, cls.matrix_size, where)
        _check_mat(b, cls.matrix_size, where)
        return a @ b

    @classmethod
    def identity(
        cls,
        batch_shape: Sequence[int] = (),
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> Tensor:
        """Identity matrices of shape (*batch_shape, matrix_size, matrix_size)."""
        return _identity(cls.matrix_size, batch_shape, dtype, device)


# ----------------------------------------------------------------------------------------
# SO(2)
# ----------------------------------------------------------------------------------------


class SO2(MatrixLieGroup):
    """Planar rotations as 2x2 matrices; tangent vectors (..., 1) hold the angle omega."""

    dim: int = 1
    matrix_size: int = 2

    @staticmethod
    def hat(v: Tensor) -> Tensor:
        """hat(omega) = omega * E, E = [[0, -1], [1, 0]]; (..., 1) -> (..., 2, 2)."""
        _check_vec(v, 1, "SO2.hat")
        w = v[..., 0]
        z = torch.zeros_like(w)
        return torch.stack([z, -w, w, z], dim=-1).reshape(*w.shape, 2, 2)

    @staticmethod
    def vee(m: Tensor) -> Tensor:
        """vee(M) = (M[1,0] - M[0,1]) / 2 (the skew part's coefficient); (..., 2, 2) -> (..., 1)."""
        _check_mat(m, 2, "SO2.vee")
        return (0.5 * (m[..., 1, 0] - m[..., 0, 1])).unsqueeze(-1)

    @staticmethod
    def from_angle(theta: Tensor) -> Tensor:
        """R(theta) = [[cos theta, -sin theta], [sin theta, cos theta]]; (...) -> (..., 2, 2)."""
        _check_float(theta, "SO2.from_angle")
        c, s = torch.cos(theta), torch.sin(theta)
        return torch.stack([c, -s, s, c], dim=-1).reshape(*theta.shape, 2, 2)

    @staticmethod
    def from_cos_sin(c: Tensor, s: Tensor, normalize: bool = False) -> Tensor:
        """[[c, -s], [s, c]] from tensors of shape (...); with ``normalize`` (c, s) is first divided by hypot(c, s)."""
        _check_float(c, "SO2.from_cos_sin")
        _check_float(s, "SO2.from_cos_sin")
        c, s = torch.broadcast_tensors(c, s)
        if normalize:
            r = torch.hypot(c, s).clamp_min(torch.finfo(c.dtype).tiny)
            c, s = c / r, s / r
        return torch.stack([c, -s, s, c], dim=-1).reshape(*c.shape, 2, 2)

    @staticmethod
    def to_angle(r: Tensor) -> Tensor:
        """theta = atan2(R[1,0] - R[0,1], R[0,0] + R[1,1]) in (-pi, pi]; (..., 2, 2) -> (...).

        Uses all four entries, so it returns the angle of the nearest rotation for a slightly
        non-orthogonal R.
        """
        _check_mat(r, 2, "SO2.to_angle")
        return torch.atan2(r[..., 1, 0] - r[..., 0, 1], r[..., 0, 0] + r[..., 1, 1])

    @staticmethod
    def wrap(d: Tensor) -> Tensor:
        """Angle (difference) wrapped to (-pi, pi]: d - 2 pi ceil(d / 2 pi - 1/2); (...) -> (...).

        That is d - 2 pi k with k = d / 2 pi rounded to the nearest integer, halves down: d itself for |d| < pi,
        +pi for d = -pi, pi, 3 pi, ...; for |d| > pi, math.remainder(d, 2 pi) up to the rounding of d / 2 pi and
        2 pi k (~|d| eps; a d within that of an odd multiple of pi may give -pi or pi + |d| eps).
        """
        _check_float(d, "SO2.wrap")
        return d - _TWO_PI * torch.ceil(d / _TWO_PI - 0.5)

    @staticmethod
    def exp(v: Tensor) -> Tensor:
        """exp(hat(omega)) = [[cos omega, -sin omega], [sin omega, cos omega]]; (..., 1) -> (..., 2, 2)."""
        _check_vec(v, 1, "SO2.exp")
        return SO2.from_angle(v[..., 0])

    @staticmethod
    def log(r: Tensor) -> Tensor:
        """log(R) = atan2(R[1,0] - R[0,1], R[0,0] + R[1,1]) in (-pi, pi]; (..., 2, 2) -> (..., 1)."""
        _check_mat(r, 2, "SO2.log")
        return SO2.to_angle(r).unsqueeze(-1)

    @staticmethod
    def inverse(r: Tensor) -> Tensor:
        """R^-1 = R^T."""
        _check_mat(r, 2, "SO2.inverse")
        return r.transpose(-1, -2)


#: The one angle wrap of the project (GEM head targets, offline evaluation): ``SO2.wrap``.
wrap_angle = SO2.wrap


# ----------------------------------------------------------------------------------------
# SO(3)
# ----------------------------------------------------------------------------------------


class SO3(MatrixLieGroup):
    """3D rotations as 3x3 matrices; tangent vectors (..., 3) = rotation vector (axis * angle)."""

    dim: int = 3
    matrix_size: int = 3

    @staticmethod
    def hat(v: Tensor) -> Tensor:
        """hat(w) = w1 E1 + w2 E2 + w3 E3 = [[0, -w3, w2], [w3, 0, -w1], [-w2, w1, 0]]; (..., 3) -> (..., 3, 3)."""
        _check_vec(v, 3, "SO3.hat")
        x, y, z = v.unbind(-1)
        o = torch.zeros_like(x)
        return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*x.shape, 3, 3)

    @staticmethod
    def vee(m: Tensor) -> Tensor:
        """vee(M) = (M[2,1] - M[1,2], M[0,2] - M[2,0], M[1,0] - M[0,1]) / 2 (coefficients of the skew part)."""
        _check_mat(m, 3, "SO3.vee")
        return 0.5 * torch.stack(
            [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], dim=-1
        )

    @staticmethod
    def exp(v: Tensor) -> Tensor:
        """Rodrigues: exp(hat w) = I + A hat(w) + B hat(w)^2, A = sin(t)/t, B = (1 - cos t)/t^2, t = |w|.

        Evaluated as (1 - B t^2) I + A hat(w) + B w w^T with A = 2 k c, B = 2 k^2,
        c = cos(t/2), k = sin(t/2)/t (Taylor in t^2 below the small-angle threshold).
        """
        _check_vec(v, 3, "SO3.exp")
        theta2 = (v * v).sum(-1)
        c, k = _half_angle(theta2)
        a = (2.0 * k * c)[..., None, None]
        b = (2.0 * k * k)[..., None, None]
        eye = _eye(3, v)
        return (1.0 - b * theta2[..., None, None]) * eye + a * SO3.hat(v) + b * (v.unsqueeze(-1) * v.unsqueeze(-2))

    @staticmethod
    def log(r: Tensor) -> Tensor:
        """log(R) = 2 atan2(|q_xyz|, q_w) q_xyz / |q_xyz| with q = to_quat(R) (w >= 0); result has |w| <= pi.

        Robust at pi (Shepperd conversion) and at 0 (Taylor of atan2(n, w)/n in (n/w)^2).
        """
        _check_mat(r, 3, "SO3.log")
        return SO3._quat_log_unit(SO3.to_quat(r))

    @staticmethod
    def inverse(r: Tensor) -> Tensor:
        """R^-1 = R^T."""
        _check_mat(r, 3, "SO3.inverse")
        return r.transpose(-1, -2)

    @staticmethod
    def angle(r: Tensor) -> Tensor:
        """Rotation angle in [0, pi]: 2 atan2(|q_xyz|, |q_w|); (..., 3, 3) -> (...)."""
        _check_mat(r, 3, "SO3.angle")
        q = SO3.to_quat(r)
        return 2.0 * torch.atan2(torch.linalg.vector_norm(q[..., 1:], dim=-1), q[..., 0].abs())

    @staticmethod
    def from_quat(q: Tensor) -> Tensor:
        """Rotation matrix of the quaternion q = (w, x, y, z) (normalised first; q must be non-zero).

        R = I + 2 [[-(y^2+z^2), xy - wz, xz + wy], [xy + wz, -(x^2+z^2), yz - wx],
                   [xz - wy, yz + wx, -(x^2+y^2)]] / |q|^2.
        """
        _check_vec(q, 4, "SO3.from_quat")
        w, x, y, z = q.unbind(-1)
        s = 2.0 / (q * q).sum(-1)
        xx, yy, zz = s * x * x, s * y * y, s * z * z
        xy, xz, yz = s * x * y, s * x * z, s * y * z
        wx, wy, wz = s * w * x, s * w * y, s * w * z
        one = torch.ones_like(w)
        return torch.stack(
            [
                one - yy - zz,
                xy - wz,
                xz + wy,
                xy + wz,
                one - xx - zz,
                yz - wx,
                xz - wy,
                yz + wx,
                one - xx - yy,
            ],
            dim=-1,
        ).reshape(*w.shape, 3, 3)

    @staticmethod
    def to_quat(r: Tensor) -> Tensor:
        """Unit quaternion (w, x, y, z) with w >= 0 of R, by Shepperd's method; (..., 3, 3) -> (..., 4).

        With d0 = 1 + tr R = 4 w^2, d1 = 1 + 2 R00 - tr R = 4 x^2, d2 = 4 y^2, d3 = 4 z^2 (the four sum to 4, so
        the largest is >= 1), the largest d_i gives its component as sqrt(d_i)/2 and the other three from
        off-diagonal sums/differences divided by 2 sqrt(d_i), e.g. for i = 0:
        w = sqrt(d0)/2, (x, y, z) = (R21 - R12, R02 - R20, R10 - R01) / (2 sqrt(d0)).
        The result is normalised and its sign chosen so that w >= 0 (at w == 0 the sign is arbitrary).
        """
        _check_mat(r, 3, "SO3.to_quat")
        r00, r01, r02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
        r10, r11, r12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
        r20, r21, r22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
        tr = r00 + r11 + r22
        d = torch.stack([1.0 + tr, 1.0 + 2.0 * r00 - tr, 1.0 + 2.0 * r11 - tr, 1.0 + 2.0 * r22 - tr], dim=-1)
        # The chosen d_i is >= 1; clamping only touches branches that are discarded, keeping their
        # (masked-out) values and gradients finite.
        s = torch.sqrt(d.clamp_min(0.5))  # (..., 4), s_i = 2 |q_i|
        inv = 0.5 / s
        s0, s1, s2, s3 = s.unbind(-1)
        i0, i1, i2, i3 = inv.unbind(-1)
        a, b, c = r21 - r12, r02 - r20, r10 - r01  # 4 w (x, y, z)
        e, f, g = r01 + r10, r02 + r20, r12 + r21  # 4 (xy, xz, yz)
        cand = torch.stack(
            [
                torch.stack([0.5 * s0, a * i0, b * i0, c * i0], dim=-1),
                torch.stack([a * i1, 0.5 * s1, e * i1, f * i1], dim=-1),
                torch.stack([b * i2, e * i2, 0.5 * s2, g * i2], dim=-1),
                torch.stack([c * i3, f * i3, g * i3, 0.5 * s3], dim=-1),
            ],
            dim=-2,
        )  # (..., 4 candidates, 4 components)
        idx = d.argmax(dim=-1, keepdim=True)  # (..., 1)
        q = torch.gather(cand, -2, idx.unsqueeze(-1).expand(*idx.shape[:-1], 1, 4)).squeeze(-2)
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        sign = torch.where(q[..., :1] < 0, -torch.ones_like(q[..., :1]), torch.ones_like(q[..., :1]))
        return q * sign

    @staticmethod
    def from_axis_angle(axis: Tensor, angle: Tensor) -> Tensor:
        """exp(angle * axis / |axis|); axis (..., 3) non-zero, angle (...) (batch dims broadcast) -> (..., 3, 3)."""
        _check_vec(axis, 3, "SO3.from_axis_angle")
        _check_float(angle, "SO3.from_axis_angle")
        u = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
        return SO3.exp(u * angle.unsqueeze(-1))

    @staticmethod
    def quat_exp(v: Tensor) -> Tensor:
        """Unit quaternion of exp(hat v): (cos(t/2), sin(t/2)/t * v), t = |v|; (..., 3) -> (..., 4)."""
        _check_vec(v, 3, "SO3.quat_exp")
        c, k = _half_angle((v * v).sum(-1))
        return torch.cat([c.unsqueeze(-1), k.unsqueeze(-1) * v], dim=-1)

    @staticmethod
    def quat_log(q: Tensor) -> Tensor:
        """Rotation vector of the quaternion q = (w, x, y, z) (normalised, sign flipped to w >= 0 first).

        log(q) = 2 atan2(n, w) / n * (x, y, z), n = |(x, y, z)|; |result| <= pi.
        """
        _check_vec(q, 4, "SO3.quat_log")
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        sign = torch.where(q[..., :1] < 0, -torch.ones_like(q[..., :1]), torch.ones_like(q[..., :1]))
        return SO3._quat_log_unit(q * sign)

    @staticmethod
    def _quat_log_unit(q: Tensor) -> Tensor:
        """quat_log for a unit quaternion with w >= 0 (no checks).

        Taylor: atan2(n, w)/n = (1 - r^2/3 + r^4/5 - r^6/7)/w, r = n/w."""
        w, xyz = q[..., 0], q[..., 1:]
        n2 = (xyz * xyz).sum(-1)
        small = n2 < 0.25 * _small_sq(q.dtype)  # theta ~ 2 n
        n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
        w_small = torch.where(small, w, torch.ones_like(w))  # w ~ 1 where small; 1 elsewhere
        r2 = n2 / (w_small * w_small)
        f = torch.where(small, _poly(r2, (1.0, -1 / 3, 1 / 5, -1 / 7)) / w_small, torch.atan2(n, w) / n)
        return (2.0 * f).unsqueeze(-1) * xyz

    @staticmethod
    def quat_mul(p: Tensor, q: Tensor) -> Tensor:
        """Hamilton product p q of (w, x, y, z) quaternions; from_quat(p q) = from_quat(p) @ from_quat(q)."""
        _check_vec(p, 4, "SO3.quat_mul")
        _check_vec(q, 4, "SO3.quat_mul")
        pw, px, py, pz = p.unbind(-1)
        qw, qx, qy, qz = q.unbind(-1)
        return torch.stack(
            [
                pw * qw - px * qx - py * qy - pz * qz,
                pw * qx + px * qw + py * qz - pz * qy,
                pw * qy - px * qz + py * qw + pz * qx,
                pw * qz + px * qy - py * qx + pz * qw,
            ],
            dim=-1,
        )


# ----------------------------------------------------------------------------------------
# SE(2)
# ----------------------------------------------------------------------------------------


class SE2(MatrixLieGroup):
    """Planar rigid motions as 3x3 homogeneous matrices; tangent (..., 3) = (omega, vx, vy)."""

    dim: int = 3
    matrix_size: int = 3

    @staticmethod
    def hat(v: Tensor) -> Tensor:
        """hat(omega, vx, vy) = [[0, -omega, vx], [omega, 0, vy], [0, 0, 0]]; (..., 3) -> (..., 3, 3)."""
        _check_vec(v, 3, "SE2.hat")
        w, vx, vy = v.unbind(-1)
        o = torch.zeros_like(w)
        return torch.stack([o, -w, vx, w, o, vy, o, o, o], dim=-1).reshape(*w.shape, 3, 3)

    @staticmethod
    def vee(m: Tensor) -> Tensor:
        """vee(M) = ((M[1,0] - M[0,1]) / 2, M[0,2], M[1,2]); (..., 3, 3) -> (..., 3)."""
        _check_mat(m, 3, "SE2.vee")
        return torch.stack([0.5 * (m[..., 1, 0] - m[..., 0, 1]), m[..., 0, 2], m[..., 1, 2]], dim=-1)

    @staticmethod
    def exp(v: Tensor) -> Tensor:
        """exp(hat(omega, u)) = [[R(omega), V u], [0, 1]], V = [[A, -B], [B, A]],
        A = sin(omega)/omega, B = (1 - cos omega)/omega (A -> 1, B -> omega/2 as omega -> 0)."""
        _check_vec(v, 3, "SE2.exp")
        w, vx, vy = v.unbind(-1)
        c, k = _half_angle(w * w)
        a = 2.0 * k * c
        b = 2.0 * k * k * w
        tx = a * vx - b * vy
        ty = b * vx + a * vy
        cw, sw = torch.cos(w), torch.sin(w)
        o, one = torch.zeros_like(w), torch.ones_like(w)
        return torch.stack([cw, -sw, tx, sw, cw, ty, o, o, one], dim=-1).reshape(*w.shape, 3, 3)

    @staticmethod
    def log(t: Tensor) -> Tensor:
        """log(T) = (omega, V^-1 t), omega = SO2.to_angle(R) in (-pi, pi],
        V^-1 = [[a, omega/2], [-omega/2, a]], a = (omega/2) cot(omega/2)."""
        _check_mat(t, 3, "SE2.log")
        w = SO2.to_angle(t[..., :2, :2])
        a = _coef_xcotx(w * w)
        tx, ty = t[..., 0, 2], t[..., 1, 2]
        h = 0.5 * w
        return torch.stack([w, a * tx + h * ty, -h * tx + a * ty], dim=-1)

    @staticmethod
    def inverse(t: Tensor) -> Tensor:
        """[[R, t], [0, 1]]^-1 = [[R^T, -R^T t], [0, 1]]."""
        _check_mat(t, 3, "SE2.inverse")
        rt = t[..., :2, :2].transpose(-1, -2)
        return _homogeneous(rt, -(rt @ t[..., :2, 2:]).squeeze(-1))

    @staticmethod
    def from_rt(r: Tensor, t: Tensor) -> Tensor:
        """[[R, t], [0, 1]] from R (..., 2, 2) and t (..., 2) (batch dims broadcast)."""
        _check_mat(r, 2, "SE2.from_rt")
        _check_vec(t, 2, "SE2.from_rt")
        return _homogeneous(r, t)

    @staticmethod
    def to_rt(t: Tensor) -> tuple[Tensor, Tensor]:
        """(R (..., 2, 2), t (..., 2)) of a homogeneous (..., 3, 3) matrix."""
        _check_mat(t, 3, "SE2.to_rt")
        return t[..., :2, :2], t[..., :2, 2]


# ----------------------------------------------------------------------------------------
# SE(3)
# ----------------------------------------------------------------------------------------


class SE3(MatrixLieGroup):
    """Rigid motions as 4x4 homogeneous matrices; tangent (..., 6) = (wx, wy, wz, vx, vy, vz), rotation first."""

    dim: int = 6
    matrix_size: int = 4

    @staticmethod
    def hat(v: Tensor) -> Tensor:
        """hat(w, u) = [[hat_so3(w), u], [0, 0]]; (..., 6) -> (..., 4, 4)."""
        _check_vec(v, 6, "SE3.hat")
        top = torch.cat([SO3.hat(v[..., :3]), v[..., 3:].unsqueeze(-1)], dim=-1)
        return torch.cat([top, torch.zeros_like(top[..., :1, :])], dim=-2)

    @staticmethod
    def vee(m: Tensor) -> Tensor:
        """vee(M) = (vee_so3(M[:3, :3]), M[:3, 3]); (..., 4, 4) -> (..., 6)."""
        _check_mat(m, 4, "SE3.vee")
        return torch.cat([SO3.vee(m[..., :3, :3]), m[..., :3, 3]], dim=-1)

    @staticmethod
    def exp(v: Tensor) -> Tensor:
        """exp(hat(w, u)) = [[exp_so3(w), V u], [0, 1]], V = I + B hat(w) + C hat(w)^2,
        B = (1 - cos t)/t^2, C = (t - sin t)/t^3, t = |w|; V u = u + B w x u + C w x (w x u)."""
        _check_vec(v, 6, "SE3.exp")
        w, u = v[..., :3], v[..., 3:]
        theta2 = (w * w).sum(-1)
        c, k = _half_angle(theta2)
        a = (2.0 * k * c)[..., None, None]
        b = 2.0 * k * k
        cc = _coef_c(theta2)
        eye = _eye(3, v)
        bm = b[..., None, None]
        r = (1.0 - bm * theta2[..., None, None]) * eye + a * SO3.hat(w) + bm * (w.unsqueeze(-1) * w.unsqueeze(-2))
        wu = torch.linalg.cross(w, u, dim=-1)
        t = u + b.unsqueeze(-1) * wu + cc.unsqueeze(-1) * torch.linalg.cross(w, wu, dim=-1)
        return _homogeneous(r, t)

    @staticmethod
    def log(t: Tensor) -> Tensor:
        """log(T) = (w, V^-1 t), w = SO3.log(R), V^-1 = I - hat(w)/2 + D hat(w)^2,
        D = (1 - (t/2) cot(t/2)) / t^2, t = |w| <= pi; V^-1 t = t - w x t / 2 + D w x (w x t)."""
        _check_mat(t, 4, "SE3.log")
        w = SO3.log(t[..., :3, :3])
        p = t[..., :3, 3]
        d = _coef_d((w * w).sum(-1))
        wp = torch.linalg.cross(w, p, dim=-1)
        u = p - 0.5 * wp + d.unsqueeze(-1) * torch.linalg.cross(w, wp, dim=-1)
        return torch.cat([w, u], dim=-1)

    @staticmethod
    def inverse(t: Tensor) -> Tensor:
        """[[R, t], [0, 1]]^-1 = [[R^T, -R^T t], [0, 1]]."""
        _check_mat(t, 4, "SE3.inverse")
        rt = t[..., :3, :3].transpose(-1, -2)
        return _homogeneous(rt, -(rt @ t[..., :3, 3:]).squeeze(-1))

    @staticmethod
    def from_rt(r: Tensor, t: Tensor) -> Tensor:
        """[[R, t], [0, 1]] from R (..., 3, 3) and t (..., 3) (batch dims broadcast)."""
        _check_mat(r, 3, "SE3.from_rt")
        _check_vec(t, 3, "SE3.from_rt")
        return _homogeneous(r, t)

    @staticmethod
    def to_rt(t: Tensor) -> tuple[Tensor, Tensor]:
        """(R (..., 3, 3), t (..., 3)) of a homogeneous (..., 4, 4) matrix."""
        _check_mat(t, 4, "SE3.to_rt")
        return t[..., :3, :3], t[..., :3, 3]


# ----------------------------------------------------------------------------------------
# R^n
# ----------------------------------------------------------------------------------------


class Rn(LieGroup):
    """Translations in R^n; elements and tangent vectors are both plain vectors (..., n), any n >= 1.

    ``Rn.dim`` is None (the methods accept any trailing size); ``Rn(n)`` is an instance whose ``dim``
    is n and whose methods are the same static functions.
    """

    dim: int | None = None
    matrix_size: int | None = None

    def __init__(self, n: int) -> None:
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise ValueError(f"Rn(n) needs a positive integer n, got {n!r}")
        self.dim = n
        self.matrix_size = n + 1

    def __repr__(self) -> str:
        return f"Rn({self.dim})"

    @staticmethod
    def hat(v: Tensor) -> Tensor:
        """hat(v) = [[0, v], [0, 0]] ((n+1) x (n+1), nilpotent); (..., n) -> (..., n+1, n+1)."""
        _check_vec(v, None, "Rn.hat")
        n = v.shape[-1]
        out = v.new_zeros(*v.shape[:-1], n + 1, n + 1)
        out[..., :n, n] = v
        return out

    @staticmethod
    def vee(m: Tensor) -> Tensor:
        """vee(M) = M[:n, n] for an (n+1) x (n+1) matrix M; (..., n+1, n+1) -> (..., n)."""
        _check_float(m, "Rn.vee")
        if m.dim() < 2 or m.shape[-1] != m.shape[-2] or m.shape[-1] < 2:
            raise ValueError(f"Rn.vee expects a tensor of shape (..., n+1, n+1) with n >= 1, got {tuple(m.shape)}")
        n = m.shape[-1] - 1
        return m[..., :n, n]

    @staticmethod
    def exp(v: Tensor) -> Tensor:
        """exp(v) = v (returns the input tensor itself, no copy)."""
        _check_vec(v, None, "Rn.exp")
        return v

    @staticmethod
    def log(x: Tensor) -> Tensor:
        """log(x) = x (returns the input tensor itself, no copy)."""
        _check_vec(x, None, "Rn.log")
        return x

    @staticmethod
    def compose(a: Tensor, b: Tensor) -> Tensor:
        """a o b = a + b (batch dims broadcast)."""
        _check_vec(a, None, "Rn.compose")
        _check_vec(b, None, "Rn.compose")
        return a + b

    @staticmethod
    def inverse(x: Tensor) -> Tensor:
        """x^-1 = -x."""
        _check_vec(x, None, "Rn.inverse")
        return -x

    @staticmethod
    def identity(
        batch_shape: Sequence[int] = (),
        *,
        n: int,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> Tensor:
        """Zero vectors of shape (*batch_shape, n) (n is required: R^n has no fixed size)."""
        return torch.zeros(
            *batch_shape, n, dtype=dtype if dtype is not None else torch.get_default_dtype(), device=device
        )

    @staticmethod
    def to_matrix(x: Tensor) -> Tensor:
        """Homogeneous translation matrix [[I, x], [0, 1]] = matrix_exp(hat(x)); (..., n) -> (..., n+1, n+1)."""
        _check_vec(x, None, "Rn.to_matrix")
        n = x.shape[-1]
        return _homogeneous(_eye(n, x).expand(*x.shape[:-1], n, n), x)
