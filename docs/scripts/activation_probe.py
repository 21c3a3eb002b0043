"""One ensemble forward at the HalfCheetah research shapes (5 members x 1600 rows, 23 -> 4 x 200 -> 34, bf16):
per-member oneDNN linear with a swish / relu / no post-op against the batched baddbmm chain (docs/performance.md).

    python docs/scripts/activation_probe.py THREADS

Prints the median ms per ensemble forward (7 rounds of 20, variants interleaved) and the same x 150 model steps,
the model work of one CEM planning step at that config.
"""

import statistics
import sys
import time

import torch

torch.set_num_threads(int(sys.argv[1]) if len(sys.argv) > 1 else 2)
E, R, IN, HID, OUT, L = 5, 1600, 23, 200, 34, 4
g = torch.Generator().manual_seed(0)
dims = [IN] + [HID] * L + [OUT]
W = [
    torch.randn(E, dims[i + 1], dims[i], generator=g).mul(dims[i] ** -0.5).to(torch.bfloat16)
    for i in range(len(dims) - 1)
]
B = [torch.randn(E, dims[i + 1], generator=g).mul(0.1).to(torch.bfloat16) for i in range(len(dims) - 1)]
WT = [w.transpose(1, 2).contiguous() for w in W]  # (E, in, out) for baddbmm
x = torch.randn(E, R, IN, generator=g).to(torch.bfloat16)
linear = torch.ops.mkldnn._linear_pointwise


def fused(attr: str) -> torch.Tensor:
    outs = []
    for m in range(E):
        y = x[m]
        for i in range(L):
            y = linear(y, W[i][m], B[i][m], attr, [], "")
        outs.append(linear(y, W[L][m], B[L][m], "none", [], ""))
    return torch.stack(outs)


def batched(act) -> torch.Tensor:
    y = x
    for i in range(L):
        y = torch.baddbmm(B[i].unsqueeze(1), y, WT[i])
        if act is not None:
            y = act(y)
    return torch.baddbmm(B[L].unsqueeze(1), y, WT[L])


variants = {
    "fused none": lambda: fused("none"),
    "fused swish": lambda: fused("swish"),
    "fused relu": lambda: fused("relu"),
    "batched none": lambda: batched(None),
    "batched silu": lambda: batched(torch.nn.functional.silu),
    "batched relu": lambda: batched(torch.relu),
    "batched hardswish": lambda: batched(torch.nn.functional.hardswish),
}
times: dict[str, list[float]] = {k: [] for k in variants}
with torch.no_grad():
    for f in variants.values():
        for _ in range(5):
            f()
    for _ in range(7):
        for k, f in variants.items():
            start = time.perf_counter()
            for _ in range(20):
                f()
            times[k].append((time.perf_counter() - start) / 20)
for k, v in times.items():
    ms = statistics.median(v) * 1e3
    print(f"{k:20s} {ms:7.3f} ms per ensemble forward -> x150 model steps = {ms * 0.15:6.3f} s per CEM step")
