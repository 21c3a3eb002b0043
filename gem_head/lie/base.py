"""The group protocol: :class:`LieGroup` (every group) and :class:`MatrixLieGroup` (the matrix groups)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence

import torch
from torch import Tensor

from gem_head.lie.kernels import _check_mat, _identity


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
