"""SO(3): 3D rotations as 3x3 matrices; Rodrigues exp, quaternion-based log, quaternion helpers."""

from __future__ import annotations

import torch
from torch import Tensor

from gem_head.lie.base import MatrixLieGroup
from gem_head.lie.kernels import _check_float, _check_mat, _check_vec, _eye, _half_angle, _poly, _small_sq


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
