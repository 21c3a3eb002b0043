"""R^n: translations; exp and log are the identity, compose is addition."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from gem_head.lie.base import LieGroup
from gem_head.lie.kernels import _check_float, _check_vec, _eye, _homogeneous


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
