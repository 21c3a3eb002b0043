"""Where a training epoch's time goes, by op group: batch gather, forward + loss, regularisers, backward, Adam,
zero_grad, holdout evaluation, and the GEMMs inside them; eager (the reference) or ``model.compile=true``.

    python docs/scripts/profile_train.py --env ant --model gem [--preset fast] [--transitions 3000] [--compile]
                                         [key=value ...]

One thread; the model and data are ``pets.bench_train``'s (random transitions). One warm-up training of one
epoch (with ``--compile``: the compilation), then one profiled training of one epoch with ``torch.profiler``:
each group is a ``record_function`` scope around the call that does it, so its time includes every op it
dispatches (the profiler's per-op cost inflates groups of many small ops: read shares, not milliseconds).
Under ``--compile`` a full minibatch is one call, "compiled step" (its GEMMs are still counted apart).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import torch
from profile_step import GEMM_OPS, scoped  # this directory: the planning step's profile
from torch.profiler import ProfilerActivity, profile, record_function

import envs
from pets import builder
from pets.config import make_config, parse_overrides
from pets.data.rollout import collect_random
from pets.learning.compiled import CompiledStep
from pets.models import make_model

GROUPS = ("gather", "forward + loss", "regularisers", "backward", "Adam", "zero_grad", "compiled step", "holdout")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="ant")
    ap.add_argument("--model", default="gem")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--transitions", type=int, default=3000)
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = make_config(envs.get(args.env).name, args.model, args.preset, parse_overrides(args.overrides))
    spec = envs.get(cfg.env)
    torch.manual_seed(cfg.seed)
    model = make_model(cfg, spec, torch.device("cpu"))
    trainer = builder.make_trainer(cfg, model)
    trainer.compile, trainer.max_epochs, trainer.patience = args.compile, 1, 2
    obs, act, nxt = (torch.as_tensor(x) for x in collect_random(spec, args.transitions, cfg.seed))

    model.member_loss = scoped("forward + loss", model.member_loss)
    model.add_regularisers = scoped("regularisers", model.add_regularisers)
    trainer.optimizer.step = scoped("Adam", trainer.optimizer.step)
    trainer.optimizer.zero_grad = scoped("zero_grad", trainer.optimizer.zero_grad)
    trainer.evaluate = scoped("holdout", trainer.evaluate)
    torch.autograd.backward = scoped("backward", torch.autograd.backward)
    CompiledStep.__call__ = scoped("compiled step", CompiledStep.__call__)
    getitem = torch.Tensor.__getitem__

    def gather(self: torch.Tensor, key: Any) -> torch.Tensor:
        if isinstance(key, torch.Tensor) and key.dtype == torch.long:
            with record_function("gather"):
                return getitem(self, key)
        return getitem(self, key)

    t0 = time.process_time()
    trainer.train(obs, act, nxt, torch.Generator().manual_seed(1))
    print(f"warm-up training (1 epoch{', compiles' if args.compile else ''}): {time.process_time() - t0:.2f} CPU s")
    t0 = time.process_time()
    trainer.train(obs, act, nxt, torch.Generator().manual_seed(2))
    print(f"one training of 1 epoch, unprofiled: {time.process_time() - t0:.3f} CPU s")
    torch.Tensor.__getitem__ = gather
    try:
        with profile(activities=[ProfilerActivity.CPU]) as prof, record_function("train"):
            trainer.train(obs, act, nxt, torch.Generator().manual_seed(3))
    finally:
        torch.Tensor.__getitem__ = getitem
    events = {e.key: e for e in prof.key_averages()}
    total = events["train"].cpu_time_total
    print(f"profiled: {total / 1e3:.1f} ms; shares of the profiled training call (1 epoch):")
    for name in GROUPS:
        if name in events:
            print(f"  {name:16s} {events[name].cpu_time_total / total:6.1%}  ({events[name].count} calls)")
    gemm = sum(events[k].self_cpu_time_total for k in GEMM_OPS if k in events)
    print(f"  {'GEMMs (inside)':16s} {gemm / total:6.1%}")
    if "TorchDynamo Cache Lookup" in events:
        print(f"  {'guards (inside)':16s} {events['TorchDynamo Cache Lookup'].self_cpu_time_total / total:6.1%}")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15, max_name_column_width=50))
    return 0


if __name__ == "__main__":
    sys.exit(main())
