"""Shared numerics of the groups: dtype thresholds, argument checks, Taylor-safe coefficients, identities."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

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
