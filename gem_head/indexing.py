"""Index selections along the last dim, prepared once: a basic slice where the indices are an ascending run (a
view, no gather), else a long tensor; the codecs and heads read and write their entries through them."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["Sel", "sel", "take", "put"]

Sel = slice | Tensor


def sel(indices: list[int]) -> Sel:
    """A basic slice when ``indices`` is a non-empty ascending run (a view, no gather), else a long tensor."""
    if indices and indices == list(range(indices[0], indices[0] + len(indices))):
        return slice(indices[0], indices[0] + len(indices))
    return torch.tensor(indices, dtype=torch.long)


def take(x: Tensor, s: Sel) -> Tensor:
    """x[..., s] along the last dim, contiguous (elementwise kernels on strided views are ~10x slower on CPU)."""
    return x[..., s].contiguous() if isinstance(s, slice) else x.index_select(-1, s)


def put(out: Tensor, s: Sel, value: Tensor) -> None:
    """out[..., s] = value along the last dim (in place)."""
    if isinstance(s, slice):
        out[..., s] = value
    else:
        out.index_copy_(-1, s, value.to(out.dtype))
