"""CPU bf16 inference of the member MLPs as oneDNN fused linear + SiLU calls, one member at a time.

Under ``torch.autocast("cpu", bfloat16)`` without autograd (the planner's ``precision=bf16`` path), each
member's layers run as ``torch.ops.mkldnn._linear_pointwise(h, W^T, b, "swish")``: the GEMM, bias and SiLU in
one oneDNN call (post-op), so the SiLU's separate memory pass goes away and a member's activations stay in
cache from layer to layer. Measured on a Zen 4 core (AVX-512 BF16), 5 members x 1600 rows x 4 x 200: 7.9 ms
per ensemble forward against 8.7 ms for the batched ``baddbmm`` + SiLU, 1.08-1.11x on the whole
HalfCheetah research planning step (docs/performance.md); the members are looped over in Python (5 x 5
calls), which the measurement includes, so it is used only from :data:`MIN_ROWS` rows per member. The weights are
transposed and cast to bf16 once per :func:`cached_weights` scope (``TrajectoryEvaluator`` opens one per call:
the weights cannot change during a rollout), else on every forward.

Numerics: bf16 inputs and weights like autocast's batched path; oneDNN applies the SiLU in fp32 before
rounding to bf16, so the outputs differ from the batched path by bf16 rounding (and are slightly closer to
fp32: tests/test_ensemble.py). Off under ``torch.compile`` (inductor fuses the tail itself), with autograd,
off CPU, and where the op is missing or oneDNN has no bf16 kernels for the CPU (AVX2-only x86: there bf16 runs
autocast's batched path); ``FUSED_CPU_BF16 = False`` turns it off.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import torch
from torch import Tensor, nn

#: Use the fused per-member path where it applies (see the module docstring).
FUSED_CPU_BF16 = True
#: Rows per member from which it is used: below, the 5 x (layers) Python calls cost more than they save
#: (measured per ensemble forward, one Zen 4 core: 0.87x at 100 rows, 0.94x at 200, 1.02x at 400, 1.04x at
#: 800, 1.10x at 1600; the fast preset has 100, the research config 1600).
MIN_ROWS = 512


def _onednn_bf16() -> bool:
    """Whether this build has the fused op and oneDNN has bf16 kernels for this CPU (x86 from AVX-512 on; on an
    AVX2-only CPU the op raises "could not create a primitive descriptor")."""
    if not (torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")):
        return False
    probe = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
    return bool(probe is not None and probe())


_AVAILABLE = _onednn_bf16()
_SCOPE = threading.local()  # .cache: {key: prepared layers} inside a cached_weights() scope of this thread


@contextlib.contextmanager
def cached_weights() -> Iterator[None]:
    """Within this scope the prepared bf16 weights are reused from one forward to the next (keyed on the
    parameters, their versions and the member selection); the caller promises not to change the weights
    inside it in a way that bypasses the version counter. Nested scopes share the outer one."""
    outer = getattr(_SCOPE, "cache", None)
    if outer is None:
        _SCOPE.cache = {}
    try:
        yield
    finally:
        if outer is None:
            _SCOPE.cache = None


def applies(h: Tensor) -> bool:
    """Whether :func:`fused_member_mlp` runs ``h`` (CPU, bf16 autocast on, no autograd, not compiling,
    at least :data:`MIN_ROWS` rows per member)."""
    return (
        FUSED_CPU_BF16
        and _AVAILABLE
        and h.shape[-2] >= MIN_ROWS
        and h.device.type == "cpu"
        and not torch.is_grad_enabled()
        and torch.is_autocast_enabled("cpu")
        and torch.get_autocast_dtype("cpu") == torch.bfloat16
        and not torch.compiler.is_compiling()
    )


def _packed(
    weights: nn.ParameterList, biases: nn.ParameterList, idx: Tensor | None
) -> list[list[tuple[Tensor, Tensor]]]:
    """Per selected member, per layer ``(W^T as (out, in), b as (out,))`` in bf16 (reused inside a
    :func:`cached_weights` scope)."""
    cache = getattr(_SCOPE, "cache", None)
    if cache is not None:
        key = (
            id(weights),
            tuple((p._version, p.data_ptr()) for p in (*weights, *biases)),
            None if idx is None else tuple(idx.tolist()),
        )
        if key in cache:
            return cache[key]
    layers = []
    for w, b in zip(weights, biases):
        if idx is not None:
            w, b = w.index_select(0, idx), b.index_select(0, idx)
        wt = w.detach().transpose(1, 2).to(torch.bfloat16, memory_format=torch.contiguous_format)
        layers.append((wt.unbind(0), b.detach().squeeze(1).to(torch.bfloat16).unbind(0)))
    members = [[(w[m], b[m]) for w, b in layers] for m in range(len(layers[0][0]))]
    if cache is not None:
        cache[key] = members
    return members


def batched_layers(
    weights: nn.ParameterList, biases: nn.ParameterList, idx: Tensor | None, dtype: torch.dtype, pad_multiple: int
) -> list[tuple[Tensor, Tensor]] | None:
    """The batched path's per-layer ``(W, b)`` of the selected members, the output layer zero-padded to a multiple of
    ``pad_multiple`` columns, cast to ``dtype``: prepared once per :func:`cached_weights` scope (the same values
    that selecting, padding and autocast's cast give on every forward, so the same results). None outside a scope
    (and while compiling): the caller prepares them itself."""
    cache = getattr(_SCOPE, "cache", None)
    if cache is None or torch.compiler.is_compiling():
        return None
    key = (
        "batched",
        id(weights),
        tuple((p._version, p.data_ptr()) for p in (*weights, *biases)),
        None if idx is None else tuple(idx.tolist()),
        dtype,
        pad_multiple,
    )
    if key not in cache:
        layers = []
        for i, (w, b) in enumerate(zip(weights, biases)):
            if idx is not None:
                w, b = w.index_select(0, idx), b.index_select(0, idx)
            pad = -w.shape[-1] % pad_multiple if i == len(weights) - 1 else 0
            if pad:
                w, b = torch.nn.functional.pad(w, (0, pad)), torch.nn.functional.pad(b, (0, pad))
            layers.append((w.detach().to(dtype), b.detach().to(dtype)))
        cache[key] = layers
    return cache[key]


def fused_member_mlp(
    h: Tensor, weights: nn.ParameterList, biases: nn.ParameterList, idx: Tensor | None, post_op: str = "swish"
) -> Tensor:
    """:func:`dynamics.networks.member_mlp` (the activation between layers as oneDNN's ``post_op``: ``swish`` for
    SiLU, ``relu``; linear output) in bf16, one member at a time; ``h`` is (B, in) shared by the members or
    (M, B, in). Returns (M, B, out) in bf16."""
    members = _packed(weights, biases, idx)
    x = h.to(torch.bfloat16)
    xs = [x] * len(members) if x.dim() == 2 else x.unbind(0)
    linear = torch.ops.mkldnn._linear_pointwise
    outs = []
    for y, layers in zip(xs, members):
        for w, b in layers[:-1]:
            y = linear(y, w, b, post_op, [], "")
        outs.append(linear(y, *layers[-1], "none", [], ""))
    return torch.stack(outs)
