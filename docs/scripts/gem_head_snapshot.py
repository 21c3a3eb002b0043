"""Snapshot every output of the GEM heads on fixed real transitions, to compare a refactor bit for bit.

    python docs/scripts/gem_head_snapshot.py OUT.pt              # write the snapshot
    python docs/scripts/gem_head_snapshot.py OUT.pt --compare REF.pt   # write, then compare with REF byte for byte

Per env of the catalogue (all have groups), on seeded random transitions (``pets.data.rollout.collect_random``) in
float32 and float64: of ``gem`` (compose right and left), ``gem-se`` (envs with a root), ``delta-groupfeat`` and
``gem2``, the targets from (obs, next_obs), the decoded prediction of those targets and of perturbed ones, the
network inputs, the Frobenius loss (with and without a scale) and its gradient, every loss kind, the group matrices,
and the names and slots the head reports. The comparison prints one line per differing key and exits 1 if any
differ.
"""

from __future__ import annotations

import hashlib
import sys

import torch

import envs
from gem_head.ablation import GroupFeatureDeltaHead
from gem_head.head import GemHead
from gem_head.se_root import GemSEHead
from gem_head.two_stage import TwoStageGemHead
from pets.data.rollout import collect_random

torch.set_num_threads(1)
STEPS = {"humanoid": 60, "ant": 120}


def head_outputs(head: GemHead, obs: torch.Tensor, act: torch.Tensor, nxt: torch.Tensor) -> dict[str, object]:
    """Every output of ``head`` on (obs, act, nxt), keyed by what it is."""
    g = torch.Generator().manual_seed(0)
    out: dict[str, object] = {"input_names": head.input_names, "target_names": head.target_names}
    out["group_slots"], out["velocity_slots"] = head.group_slots, head.velocity_slots
    y = head.targets(obs, nxt)
    noisy = y + 0.3 * torch.randn(y.shape, generator=g, dtype=torch.float64).to(y.dtype)
    out.update(targets=y, decoded=head.next_obs(obs, y), decoded_noisy=head.next_obs(obs, noisy))
    out["inputs"] = head.inputs(obs, act)
    out["so2"], out["so3"] = head.group_matrices(obs)
    e_obs, e_nxt, e_y, e_noisy = (x.reshape(2, -1, x.shape[-1]) for x in (obs, nxt, y, noisy))
    scale = 0.5 + torch.rand(head.target_dim, generator=g, dtype=torch.float64).to(y.dtype)
    mean = e_noisy.clone().requires_grad_(True)
    frob = head.frobenius_loss(mean, e_y, e_obs, e_nxt)
    (grad,) = torch.autograd.grad(frob.sum(), mean)
    out.update(frobenius=frob.detach(), frobenius_grad=grad)
    out["frobenius_scaled"] = head.frobenius_loss(e_noisy, e_y, e_obs, e_nxt, scale)
    logvar = torch.zeros_like(e_y) - 1.0
    for kind in ("nll", "frobenius", "nll+frobenius"):
        head.loss_kind = kind
        out[f"loss_{kind}"] = head.loss(e_noisy, logvar, e_y, e_obs, e_nxt, scale)
    return out


def snapshot() -> dict[str, object]:
    """All outputs of all heads on all envs, flat keys ENV/HEAD/DTYPE/WHAT."""
    snap: dict[str, object] = {}
    for name in envs.names():
        spec = envs.get(name)
        data = [torch.as_tensor(x, dtype=torch.float64) for x in collect_random(spec, STEPS.get(name, 200), 0)]
        n = data[0].shape[0] - data[0].shape[0] % 2
        heads = {f"gem-{c}": GemHead(spec.layout, spec.act_dim, compose=c) for c in ("right", "left")}
        heads["gem2"] = TwoStageGemHead(spec.layout, spec.act_dim)
        if spec.layout.root is not None:
            heads["gem-se"] = GemSEHead(spec.layout, spec.act_dim)
        for dtype in (torch.float64, torch.float32):
            obs, act, nxt = (x[:n].to(dtype) for x in data)
            for label, head in heads.items():
                for what, value in head_outputs(head, obs, act, nxt).items():
                    snap[f"{name}/{label}/{dtype}/{what}"] = value
            snap[f"{name}/delta-groupfeat/{dtype}/inputs"] = GroupFeatureDeltaHead(spec.layout, spec.act_dim).inputs(
                obs, act
            )
    return snap


def digest(value: object) -> str:
    """sha256 of a tensor's bytes (with dtype and shape) or of a value's repr."""
    if isinstance(value, torch.Tensor):
        raw = repr((value.dtype, tuple(value.shape))).encode() + value.detach().contiguous().numpy().tobytes()
    else:
        raw = repr(value).encode()
    return hashlib.sha256(raw).hexdigest()


if __name__ == "__main__":
    path = sys.argv[1]
    snap = snapshot()
    torch.save(snap, path)
    total = hashlib.sha256("".join(f"{k}={digest(v)}\n" for k, v in sorted(snap.items())).encode()).hexdigest()
    print(f"{len(snap)} outputs, overall sha256 {total}")
    if len(sys.argv) > 3 and sys.argv[2] == "--compare":
        ref = torch.load(sys.argv[3], weights_only=False)
        bad = [
            k
            for k in sorted(set(ref) | set(snap))
            if k not in ref or k not in snap or digest(ref[k]) != digest(snap[k])
        ]
        for k in bad:
            print(f"DIFFERS: {k}")
        print(f"{len(ref)} reference outputs, {len(bad)} differ")
        sys.exit(1 if bad else 0)
