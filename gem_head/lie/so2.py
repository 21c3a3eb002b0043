"""SO(2): planar rotations as 2x2 matrices; the one angle wrap of the project."""

from __future__ import annotations

import torch
from torch import Tensor

from gem_head.lie.base import MatrixLieGroup
from gem_head.lie.kernels import _TWO_PI, _check_float, _check_mat, _check_vec


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
