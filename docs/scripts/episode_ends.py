"""How the episodes of an online run ended: one CSV row per episode in its replay buffer (the seed data's included).

    python docs/scripts/episode_ends.py RUN_DIR [RUN_DIR ...] [--out OUT.csv]

Columns: run (the directory's name), episode, steps, fell (the env's own termination function on its last
transition), action_sq (the mean over its steps of the action's squared norm: Ant's control cost is 0.5 times it),
and for a body with a free root (an ``Rn`` translation of 3 and an ``SO3_quat`` rotation: Ant,
Humanoid) the torso's height and the cosine between the torso's up axis and the world's up at the episode's last
state (1 upright, -1 on its back). On Ant a fall is a height out of ``healthy_z_range`` = [0.2, 1.0]: above it, a
jump; below, a collapse.
Reads ``config.yaml`` and ``checkpoint.pt`` (the buffer is in the checkpoint); writes to stdout without --out.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

import envs
from pets.planning.value import episode_ends


def rows(run_dir: Path) -> list[dict[str, object]]:
    """One row per episode of ``run_dir``'s replay buffer."""
    spec = envs.get(OmegaConf.load(run_dir / "config.yaml").env)
    buffer = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=False)["buffer"]
    obs, act, nxt = (torch.as_tensor(buffer[k]) for k in ("obs", "act", "next_obs"))
    last = torch.nonzero(episode_ends(obs, nxt)).flatten()
    fell = spec.terminated(obs[last], act[last], nxt[last])
    root = spec.layout.root
    out = []
    for i, (end, start) in enumerate(zip(last.tolist(), [0, *(last + 1).tolist()])):
        row: dict[str, object] = {"run": run_dir.name, "episode": i, "steps": end - start + 1, "fell": int(fell[i])}
        row["action_sq"] = round(float(act[start : end + 1].square().sum(-1).mean()), 3)
        if root is not None and spec.layout.group(root[1]).kind == "SO3_quat":
            z = spec.layout.group(root[0]).indices[2]
            w, x, y, _ = (float(v) for v in nxt[end, list(spec.layout.group(root[1]).indices)])
            row |= {"height": round(float(nxt[end, z]), 3), "up_cos": round(1 - 2 * (x * x + y * y), 3)}
        out.append(row)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    found = [row for run_dir in args.run_dirs for row in rows(run_dir)]
    f = args.out.open("w", newline="") if args.out else sys.stdout
    writer = csv.DictWriter(f, fieldnames=list(found[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(found)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
