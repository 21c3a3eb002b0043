"""SE(2) and SE(3): rigid motions as homogeneous matrices, rotation first."""

from __future__ import annotations

import torch
from torch import Tensor

from gem_head.lie.base import MatrixLieGroup
from gem_head.lie.kernels import _check_mat, _check_vec, _coef_c, _coef_d, _coef_xcotx, _eye, _half_angle, _homogeneous
from gem_head.lie.so2 import SO2
from gem_head.lie.so3 import SO3


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
        w = v[..., 0]
        tx, ty = SE2.v_apply(w, v[..., 1:]).unbind(-1)
        cw, sw = torch.cos(w), torch.sin(w)
        o, one = torch.zeros_like(w), torch.ones_like(w)
        return torch.stack([cw, -sw, tx, sw, cw, ty, o, o, one], dim=-1).reshape(*w.shape, 3, 3)

    @staticmethod
    def v_apply(w: Tensor, u: Tensor) -> Tensor:
        """V(omega) u: the translation of exp(hat(omega, u)); w (...), u (..., 2) -> (..., 2)."""
        c, k = _half_angle(w * w)
        a = 2.0 * k * c
        b = 2.0 * k * k * w
        vx, vy = u.unbind(-1)
        return torch.stack([a * vx - b * vy, b * vx + a * vy], dim=-1)

    @staticmethod
    def v_inv_apply(w: Tensor, t: Tensor) -> Tensor:
        """V(omega)^-1 t: the translation part of log([[R(omega), t], [0, 1]]); w (...), t (..., 2) -> (..., 2)."""
        a = _coef_xcotx(w * w)
        h = 0.5 * w
        tx, ty = t.unbind(-1)
        return torch.stack([a * tx + h * ty, -h * tx + a * ty], dim=-1)

    @staticmethod
    def log(t: Tensor) -> Tensor:
        """log(T) = (omega, V^-1 t), omega = SO2.to_angle(R) in (-pi, pi],
        V^-1 = [[a, omega/2], [-omega/2, a]], a = (omega/2) cot(omega/2)."""
        _check_mat(t, 3, "SE2.log")
        w = SO2.to_angle(t[..., :2, :2])
        return torch.cat([w.unsqueeze(-1), SE2.v_inv_apply(w, t[..., :2, 2])], dim=-1)

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
        eye = _eye(3, v)
        bm = b[..., None, None]
        r = (1.0 - bm * theta2[..., None, None]) * eye + a * SO3.hat(w) + bm * (w.unsqueeze(-1) * w.unsqueeze(-2))
        return _homogeneous(r, SE3.v_apply(w, u))

    @staticmethod
    def v_apply(w: Tensor, u: Tensor) -> Tensor:
        """V(w) u = u + B w x u + C w x (w x u): the translation of exp(hat(w, u)); (..., 3), (..., 3) -> (..., 3)."""
        theta2 = (w * w).sum(-1)
        _, k = _half_angle(theta2)
        wu = torch.linalg.cross(w, u, dim=-1)
        return u + (2.0 * k * k).unsqueeze(-1) * wu + _coef_c(theta2).unsqueeze(-1) * torch.linalg.cross(w, wu, dim=-1)

    @staticmethod
    def v_inv_apply(w: Tensor, t: Tensor) -> Tensor:
        """V(w)^-1 t = t - w x t / 2 + D w x (w x t): the translation part of log([[exp(w), t], [0, 1]])."""
        d = _coef_d((w * w).sum(-1))
        wt = torch.linalg.cross(w, t, dim=-1)
        return t - 0.5 * wt + d.unsqueeze(-1) * torch.linalg.cross(w, wt, dim=-1)

    @staticmethod
    def log(t: Tensor) -> Tensor:
        """log(T) = (w, V^-1 t), w = SO3.log(R), V^-1 = I - hat(w)/2 + D hat(w)^2,
        D = (1 - (t/2) cot(t/2)) / t^2, t = |w| <= pi; V^-1 t = t - w x t / 2 + D w x (w x t)."""
        _check_mat(t, 4, "SE3.log")
        w = SO3.log(t[..., :3, :3])
        return torch.cat([w, SE3.v_inv_apply(w, t[..., :3, 3])], dim=-1)

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
