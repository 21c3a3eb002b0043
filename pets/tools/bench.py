"""Planning-step benchmark: median seconds per MPC step, achieved model GFLOP/s, machine matmul peaks.

    python -m pets.bench --env halfcheetah --model delta [--preset fast] [--device cpu] [--repeats 5]
                         [--compare] [--json FILE] [key=value ...]

The model is fitted briefly on real random-action transitions first, so the rollouts run through
realistic (normalised, finite) states. Every row times ``--repeats`` planning steps (``agent.act``
from a fresh plan) after one warm-up step (reported separately: it includes any compilation);
figures are medians. With ``--compare`` one run times, on the same model and start state, the
rows: CEM eager fp32 (the precise path), CEM compiled fp32, CEM eager bf16, CEM compiled bf16,
iCEM eager fp32, iCEM compiled bf16 and MPPI eager fp32 (the configured path, by default
``planner.precision=auto`` resolved on this machine, is marked ``default``, or added as a row when it is
none of these; where bf16 is emulated the bf16 rows are left out), the configured path with the other
``model.activation`` (relu, or silu; the same weights, so its cost, not its accuracy), then the kernel
floor at the config's shapes (:func:`kernel_floor`: the model's GEMMs + bias alone, fp32 and bf16, and bf16
with SiLU); the rows take turns within each repeat, so a change in machine load hits all of them alike.
Use ``threads=1`` on a shared machine. The header names the machine (CPU model and bf16 ISA: AMX, AVX-512 BF16 or
none, :mod:`pets.runs.hardware`; usable CPUs, torch threads, torch and Python versions, the GPU;
:func:`pets.tools.measure.machine`) and the command.

Columns: wall and process-CPU seconds per step (CPU time is the steadier figure on a loaded
machine; with one thread it is close to the compute time), model GFLOP per step (counted from the
candidates the planner actually evaluated: 2 x multiply-adds of one member's MLP per particle row
and step), achieved GFLOP/s (on wall time), the fraction of the measured GEMM peak of the row's
precision (fp32 rows: fp32 peak, bf16 rows: bf16 peak; 2048^3 products) and the peak memory of
one more (untimed) step: on CUDA ``torch.cuda.max_memory_allocated`` above the allocation before
the step; on Linux CPUs the growth of the resident set during the step (free heap memory is first
handed back with glibc's ``malloc_trim(0)``, then VmHWM is reset through ``/proc/self/clear_refs``;
the figure is VmHWM after the step minus VmRSS before it: the step's peak working memory, model
weights and earlier state excluded), elsewhere the growth of ``ru_maxrss`` (0 once an earlier,
larger peak happened).
``--json FILE`` writes the precise row's ``seconds_per_step``, ``model_gflops``, ``peak_gflops``
(fp32) and ``model_gflop_per_step``, plus every row under ``rows`` and the machine and command under ``machine``.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

import envs
from pets import builder
from pets.config import ConfigError, make_config, parse_overrides, validate
from pets.data.rollout import collect_random
from pets.models import make_model
from pets.planning.particles import CANDIDATE_TABLE
from pets.planning.planners import PLANNER_CLASSES
from pets.runs.fileio import writable_dir_error
from pets.runs.hardware import EMULATED_BF16_SLOWDOWN, cpu_isa, native_bf16
from pets.tools.cli import OneLineParser, fail, import_given, positive_int, write_json_result
from pets.tools.measure import (
    PeakMemory,
    command_line,
    kernel_floor,
    machine,
    machine_line,
    matmul_peak_gflops,
    model_flops_per_row,
    sync,
)

#: (label, planner overrides) of the ``--compare`` rows; the first is the precise reference.
COMPARE_ROWS: list[tuple[str, dict[str, Any]]] = [
    ("cem fp32 eager", {"name": "cem", "precision": "fp32", "compile": False}),
    ("cem fp32 compiled", {"name": "cem", "precision": "fp32", "compile": True}),
    ("cem bf16 eager", {"name": "cem", "precision": "bf16", "compile": False}),
    ("cem bf16 compiled", {"name": "cem", "precision": "bf16", "compile": True}),
    ("icem fp32 eager", {"name": "icem", "precision": "fp32", "compile": False}),
    ("icem bf16 compiled", {"name": "icem", "precision": "bf16", "compile": True}),
    ("mppi fp32 eager", {"name": "mppi", "precision": "fp32", "compile": False}),
]


def compare_rows(cfg: DictConfig, bf16: bool = True) -> list[tuple[str, dict[str, Any]]]:
    """:data:`COMPARE_ROWS` with the configured path (the defaults: ``planner.precision=auto`` resolved on this
    machine, ``planner.compile``) marked ``default``; appended as a row of its own when none of them is it. With
    feedback candidates the iCEM rows are left out; with ``bf16=False`` (a CPU where bf16 is emulated) the bf16
    rows, unless the configured path is one. Last, the configured path with the other ``model.activation`` (its
    ``activation`` key; timed on the same weights: the activation's cost, not its accuracy)."""
    p = cfg.planner
    here = {"name": p.name, "precision": p.precision, "compile": bool(p.compile)}
    rows = [(f"default: {label}" if planner == here else label, planner) for label, planner in COMPARE_ROWS]
    if not CANDIDATE_TABLE[p.candidates].searches_actions:  # only the planners that search gains (pets.config)
        bound, std = p.feedback.gain_bound, p.feedback.gain_std
        rows = [(label, q) for label, q in rows if PLANNER_CLASSES[q["name"]].gain_options(bound, std) is not None]
    if not bf16:
        rows = [(label, planner) for label, planner in rows if planner["precision"] != "bf16" or planner == here]
    label = f"{p.name} {p.precision} {'compiled' if p.compile else 'eager'}"
    if here not in [planner for _, planner in COMPARE_ROWS]:
        rows.append((f"default: {label}", here))
    other = "relu" if cfg.model.activation == "silu" else "silu"
    return [*rows, (f"{label} {other}", {**here, "activation": other})]


# ---------------------------------------------------------------------------------------------- timing
class _CountingEvaluator:
    """Wraps a TrajectoryEvaluator and counts the model rows (one member, one step) it computes."""

    def __init__(self, evaluator: Any) -> None:
        self.evaluator = evaluator
        self.rows = 0

    def __call__(self, obs0: Tensor, actions: Tensor, generator: torch.Generator | None = None) -> Tensor:
        ev = self.evaluator
        n, h = actions.shape[:2]
        self.rows += h * ev.model_rows(n, actions.device)
        return ev(obs0, actions, generator)


def prepare(cfg: DictConfig) -> dict[str, Any]:
    """Env spec, a briefly trained model (400 random transitions, 2 epochs), those transitions (``data``: obs,
    act, next obs on the device) and a start state."""
    spec = envs.get(cfg.env)
    device = builder.resolve_device(cfg.device)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    model = make_model(cfg, spec, device)
    trainer = builder.make_trainer(cfg, model)
    obs, act, nxt = (torch.as_tensor(x, device=device) for x in collect_random(spec, 400, cfg.seed))
    trainer.max_epochs, trainer.iterations = 2, 0  # 2 epochs, whatever schedule the config trains by
    trainer.train(obs, act, nxt, torch.Generator(device=device).manual_seed(cfg.seed))
    model.eval()
    return {"spec": spec, "device": device, "model": model, "data": (obs, act, nxt), "start": obs[-1].cpu().numpy()}


def _row_config(cfg: DictConfig, planner: dict[str, Any]) -> DictConfig:
    """The config of a row: ``planner`` merged into ``cfg.planner``, its ``activation`` key into ``cfg.model``."""
    planner = dict(planner)
    model = {"activation": planner.pop("activation")} if "activation" in planner else {}
    row = OmegaConf.merge(cfg, {"planner": planner, "model": model})
    validate(row)
    return row


@contextlib.contextmanager
def _activation(network: Any, activation: str) -> Iterator[None]:
    """The shared model's network with a row's activation for the duration of one step."""
    before, network.activation = network.activation, activation
    try:
        yield
    finally:
        network.activation = before


def time_rows(
    cfg: DictConfig, rows: list[tuple[str, dict[str, Any]]], repeats: int = 5, parts: dict[str, Any] | None = None
) -> list[dict[str, Any]]:
    """Time every row (label, planner overrides, optionally ``activation``) on one model: a warm-up step each,
    then ``repeats`` rounds in which every row plans once. Returns one dict of figures per row."""
    if not isinstance(repeats, int) or repeats < 1:
        raise ValueError(f"repeats must be a positive int, got {repeats!r}")
    parts = prepare(cfg) if parts is None else parts
    spec, device, model, start = (parts[k] for k in ("spec", "device", "model", "start"))
    head = model.head
    flops_row = model_flops_per_row(head.input_dim, head.target_dim, cfg.model.hidden_size, cfg.model.num_layers)
    agents, counters, results = [], [], []
    for label, planner in rows:
        row_cfg = _row_config(cfg, planner)
        gen = torch.Generator(device=device).manual_seed(cfg.seed)
        agent = builder.make_agent(row_cfg, spec, model, device, gen)
        counter = _CountingEvaluator(agent.evaluator)
        agent.evaluator = counter
        agent.reset()
        sync(device)
        t0 = time.perf_counter()
        with _activation(model.network, row_cfg.model.activation):
            agent.act(start)  # warm-up (compiles the compiled rows)
        sync(device)
        first = time.perf_counter() - t0
        agents.append(agent)
        counters.append(counter)
        results.append(
            {
                "label": label,
                "planner": row_cfg.planner.name,
                "precision": row_cfg.planner.precision,
                "compile": bool(row_cfg.planner.compile),
                "activation": row_cfg.model.activation,
                "first_step_seconds": first,
                "wall": [],
                "cpu": [],
                "rows": [],
            }
        )
    for _ in range(repeats):
        for agent, counter, res in zip(agents, counters, results):
            agent.reset()
            counter.rows = 0
            sync(device)
            with _activation(model.network, res["activation"]):
                t0, c0 = time.perf_counter(), time.process_time()
                agent.act(start)
                sync(device)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            res["wall"].append(wall)
            res["cpu"].append(cpu)
            res["rows"].append(counter.rows)
    for agent, res in zip(agents, results):  # memory: one more step each, untimed (malloc_trim costs page faults)
        agent.reset()
        with PeakMemory(device) as mem, _activation(model.network, res["activation"]):
            agent.act(start)
        res["mem"] = mem.peak_mib
    out = []
    for res in results:
        seconds = statistics.median(res["wall"])
        gflop = statistics.median(res["rows"]) * flops_row / 1e9
        out.append(
            {
                "label": res["label"],
                "planner": res["planner"],
                "precision": res["precision"],
                "compile": res["compile"],
                "activation": res["activation"],
                "seconds_per_step": seconds,
                "cpu_seconds_per_step": statistics.median(res["cpu"]),
                "first_step_seconds": res["first_step_seconds"],
                "model_gflop_per_step": gflop,
                "model_gflops": gflop / seconds,
                "peak_memory_mib": res["mem"],
            }
        )
    return out


def benchmark(cfg: DictConfig, repeats: int = 5) -> dict[str, float]:
    """Time ``repeats`` planning steps of the configured agent; return the figures as a dict."""
    p = cfg.planner
    (row,) = time_rows(cfg, [(f"{p.name} {p.precision} {'compiled' if p.compile else 'eager'}", {})], repeats)
    device = builder.resolve_device(cfg.device)
    row["peak_gflops"] = matmul_peak_gflops(device)
    if p.precision == "bf16":
        row["peak_gflops_bf16"] = matmul_peak_gflops(device, torch.bfloat16)
    return row


def bf16_is_native(device: torch.device) -> bool:
    """Whether bf16 rows are worth timing on ``device``: CUDA, or a CPU with native bf16 matmul (elsewhere an
    emulated bf16 GEMM is ~35x slower than fp32, :data:`pets.runs.hardware.EMULATED_BF16_SLOWDOWN`: minutes a step)."""
    return device.type == "cuda" or native_bf16("cpu")


def compare(cfg: DictConfig, repeats: int = 5) -> dict[str, Any]:
    """The ``--compare`` rows on one model, the fp32 and bf16 GEMM peaks, and the precise row's figures (bf16
    rows, peak and floor only where bf16 is native, :func:`bf16_is_native`; the bf16 peak is None elsewhere)."""
    device = builder.resolve_device(cfg.device)
    bf16 = bf16_is_native(device)
    parts = prepare(cfg)
    rows = time_rows(cfg, compare_rows(cfg, bf16), repeats, parts)
    peaks = {"fp32": matmul_peak_gflops(device), "bf16": matmul_peak_gflops(device, torch.bfloat16) if bf16 else None}
    if peaks["bf16"] is None and any(r["precision"] == "bf16" for r in rows):  # the configured path asked for it
        peaks["bf16"] = matmul_peak_gflops(device, torch.bfloat16, repeats=1)
    head = parts["model"].head
    floor = kernel_floor(cfg, head.input_dim, head.target_dim, device, bf16=bf16)
    base = rows[0]
    for r in rows:
        r["fraction_of_peak"] = r["model_gflops"] / peaks[r["precision"]]
        r["speedup_wall"] = base["seconds_per_step"] / r["seconds_per_step"]
        r["speedup_cpu"] = base["cpu_seconds_per_step"] / r["cpu_seconds_per_step"]
    keys = ("seconds_per_step", "cpu_seconds_per_step", "model_gflops", "model_gflop_per_step")
    return {
        **{k: base[k] for k in keys},
        "peak_gflops": peaks["fp32"],
        "peak_gflops_bf16": peaks["bf16"],
        "floor": floor,
        "rows": rows,
    }


def _print_rows(rows: list[dict[str, Any]], repeats: int) -> None:
    print(
        f"{'row':<28} {'wall s':>8} {'cpu s':>8} {'x wall':>7} {'x cpu':>6} {'first s':>8} {'GFLOP':>7} "
        f"{'GFLOP/s':>8} {'% peak':>7} {'mem MiB':>8}   (medians of {repeats} steps)"
    )
    for r in rows:
        print(
            f"{r['label']:<28} {r['seconds_per_step']:8.3f} {r['cpu_seconds_per_step']:8.3f} "
            f"{r.get('speedup_wall', 1.0):7.2f} {r.get('speedup_cpu', 1.0):6.2f} {r['first_step_seconds']:8.2f} "
            f"{r['model_gflop_per_step']:7.2f} {r['model_gflops']:8.1f} {100 * r.get('fraction_of_peak', 0.0):6.0f}% "
            f"{r['peak_memory_mib']:8.1f}"
        )


def _arguments(argv: list[str] | None) -> tuple[argparse.Namespace, DictConfig]:
    """The options and the config, every check done before any timing; bad input exits 2 with one line."""
    from pets.config import HEADS, PRESETS
    from pets.models import unknown_model

    ap = OneLineParser(prog="pets.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="halfcheetah", help="a catalogue name, a gymnasium id or package.module:ATTR")
    ap.add_argument("--model", default="delta", help=f"dynamics model: {', '.join(HEADS)} or your own (imports=[...])")
    ap.add_argument("--preset", choices=tuple(PRESETS), default="research")
    ap.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu")
    ap.add_argument("--repeats", type=positive_int, default=5, help="timed steps per row (default 5; medians)")
    ap.add_argument(
        "--compare",
        action="store_true",
        help="time eager fp32 / compiled / bf16 / compiled+bf16 CEM, iCEM and MPPI in one run",
    )
    ap.add_argument("--json", metavar="FILE", help="also write the figures (and the machine) as JSON")
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. threads=1")
    args = ap.parse_intermixed_args(argv)
    try:
        import_given(args.overrides)  # your own models register there: before --model is looked up
        if problem := unknown_model(args.model):
            raise ConfigError(problem)
        overrides = parse_overrides(args.overrides)
        overrides["device"] = args.device
        cfg = make_config(envs.get(args.env).name, args.model, args.preset, overrides)
        builder.resolve_device(cfg.device)  # --device cuda without one: one line (was a traceback)
        builder.check_memory(cfg, envs.get(cfg.env), steps=0)  # a planner this machine cannot hold: one line
        if args.json is not None and Path(args.json).is_dir():
            raise ConfigError(
                f"--json {args.json} is a directory; give a file name, e.g. {Path(args.json) / 'bench.json'}"
            )
        problem = None if args.json is None else writable_dir_error(Path(args.json).resolve().parent)
        if problem:  # before the timing, not after it
            raise ConfigError(f"cannot write --json {args.json}: {problem}")
    except (ConfigError, ValueError) as err:
        fail("pets.bench", str(err))
    return args, cfg


def main(argv: list[str] | None = None) -> int:
    args, cfg = _arguments(argv)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    p = cfg.planner
    print(
        f"{cfg.env} / {cfg.head} on {cfg.device}: population {p.population}, "
        f"{p.particles} particles, horizon {p.horizon}, {p.iterations} iterations, ensemble {cfg.model.ensemble_size}"
        f"x{cfg.model.num_layers}x{cfg.model.hidden_size}, propagation {p.propagation}"
    )
    where = {**machine(builder.resolve_device(cfg.device)), "command": command_line("pets.bench", argv)}
    print(f"{machine_line(where)}\ncommand: {where['command']}")
    print(
        f"CPU bf16 ISA: {cpu_isa()}; the default path here (planner.precision=auto resolved, "
        f"planner.compile={str(p.compile).lower()}): {p.name} {p.precision} {'compiled' if p.compile else 'eager'}"
    )
    if args.compare:
        if not bf16_is_native(builder.resolve_device(cfg.device)):
            print(
                f"bf16 rows left out: bf16 is emulated on this CPU (~{EMULATED_BF16_SLOWDOWN}x slower than fp32 per "
                "GEMM, minutes per step); time one with planner.precision=bf16 and no --compare"
            )
        res = compare(cfg, args.repeats)
        bf16_peak = res["peak_gflops_bf16"]
        print(
            f"measured GEMM peak (2048^3): fp32 {res['peak_gflops']:.1f} GFLOP/s, "
            f"bf16 {'not timed' if bf16_peak is None else f'{bf16_peak:.1f} GFLOP/s'}"
        )
        _print_rows(res["rows"], args.repeats)
        fl = res["floor"]
        bf16_floor = (
            f", bf16 {fl['bf16_gemm_seconds_per_step']:.3f}, "
            f"bf16 GEMMs + SiLU {fl['bf16_gemm_silu_seconds_per_step']:.3f}"
            if "bf16_gemm_seconds_per_step" in fl
            else ""
        )
        print(
            "kernel floor at these shapes (s per CEM step; the model's GEMMs + bias alone, see kernel_floor): "
            f"fp32 {fl['fp32_gemm_seconds_per_step']:.3f}{bf16_floor}"
        )
    else:
        res = benchmark(cfg, args.repeats)
        peak = res["peak_gflops_bf16"] if p.precision == "bf16" else res["peak_gflops"]
        print(
            f"seconds per planning step (median of {args.repeats}): {res['seconds_per_step']:.3f} "
            f"(process CPU {res['cpu_seconds_per_step']:.3f}; first step {res['first_step_seconds']:.2f})"
        )
        print(
            f"model work per step: {res['model_gflop_per_step']:.1f} GFLOP -> {res['model_gflops']:.1f} GFLOP/s "
            f"({100 * res['model_gflops'] / peak:.0f}% of the measured {p.precision} matmul peak "
            f"{peak:.1f} GFLOP/s); peak memory of a step {res['peak_memory_mib']:.1f} MiB"
        )
    if args.json:
        write_json_result("pets.bench", Path(args.json), {**res, "machine": where})
    return 0


if __name__ == "__main__":
    sys.exit(main())
