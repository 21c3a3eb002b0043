"""precision=auto (pets.runs.hardware, pets.config) and bf16 model training (issue 13)."""

import contextlib
import math

import pytest
import torch
from omegaconf import OmegaConf

from pets.config import ConfigError, load_config, make_config
from pets.runs import hardware
from tests.bf16 import emulated_bf16_warning

AMX = frozenset({"avx512f", "amx_tile", "amx_bf16", "avx512_bf16"})
ZEN4 = frozenset({"avx512f", "avx512_bf16"})
OLD = frozenset({"avx2", "fma"})

#: Documented tolerance (docs/performance.md): holdout error after a fixed budget, bf16 against fp32, relative.
BF16_TRAIN_RELATIVE = 0.01


def test_cpu_isa_and_auto_resolution_per_machine_kind(monkeypatch):
    assert [hardware.cpu_isa(f) for f in (AMX, ZEN4, OLD)] == ["AMX", "AVX-512 BF16", "no native bf16"]
    for flags, expected in ((AMX, "bf16"), (ZEN4, "bf16"), (OLD, "fp32")):
        assert hardware.resolve_precision("auto", "cpu", flags) == expected
        assert hardware.resolve_precision("fp32", "cpu", flags) == "fp32"  # explicit values stay
        assert hardware.resolve_precision("bf16", "cpu", flags) == "bf16"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    for supported in (True, False):  # CUDA: fp32 either way (bf16 eager measured slower: launch-bound)
        monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda s=supported: s)
        assert hardware.native_bf16("cuda") is supported
        assert hardware.resolve_precision("auto", "cuda", AMX) == "fp32"
        assert hardware.resolve_precision("auto", "auto", AMX) == "fp32"  # device=auto picks CUDA here
        assert hardware.resolve_precision("bf16", "cuda", AMX) == "bf16"


def test_bf16_where_it_would_be_emulated_warns_when_the_run_is_built_with_what_to_do(monkeypatch, recwarn):
    """On a CPU without native bf16 (AVX2 only: an emulated bf16 GEMM measured 35x slower than fp32 on a Zen 3),
    building a planner or trainer in bf16 (asked for, or a resumed run that recorded it) warns, once per key;
    reading such a config does not (a study's rerun reads every run's). auto resolves to fp32 there and stays
    quiet, and so does bf16 where the CPU has it."""
    import envs
    from pets import builder
    from pets.models import make_model

    cpu, spec = torch.device("cpu"), envs.get("reacher")

    def build(**overrides):
        cfg = make_config("reacher", preset="fast", overrides={"device": "cpu", **overrides})
        model = make_model(cfg, spec, cpu)
        builder.make_trainer(cfg, model)
        builder.make_agent(cfg, spec, model, cpu, torch.Generator())
        return cfg

    monkeypatch.setattr(hardware, "cpu_flags", lambda: OLD)
    cfg = make_config("reacher", overrides={"device": "cpu", "planner.precision": "bf16"})
    assert cfg.planner.precision == "bf16" and cfg.model.precision == "fp32"
    assert not [w for w in recwarn if "emulated" in str(w.message)]  # a config alone: quiet
    with pytest.warns(RuntimeWarning, match=r"planner.precision=bf16 on a CPU without native bf16.*emulated") as got:
        build(**{"planner.precision": "bf16"})
    emulated = [str(w.message) for w in got if "emulated" in str(w.message)]
    assert len(emulated) == 1 and "use planner.precision=fp32 or auto" in emulated[0]  # model: fp32, quiet
    with pytest.warns(RuntimeWarning, match=r"model.precision=bf16 on a CPU without native bf16"):
        build(**{"model.precision": "bf16"})
    recwarn.clear()
    assert build().planner.precision == "fp32"
    for flags in (ZEN4, AMX):
        monkeypatch.setattr(hardware, "cpu_flags", lambda f=flags: f)
        build(**{"planner.precision": "bf16", "model.precision": "bf16"})
    assert not [w for w in recwarn if "emulated" in str(w.message)]


def test_the_config_default_is_auto_resolved_once_and_recorded(tmp_path, monkeypatch):
    native = hardware.device_type("auto") == "cpu" and hardware.native_bf16("cpu")  # auto: bf16 on such CPUs only
    cfg = make_config("halfcheetah")
    assert cfg.planner.precision == cfg.model.precision == ("bf16" if native else "fp32")
    for flags, expected in ((ZEN4, "bf16"), (OLD, "fp32")):
        monkeypatch.setattr(hardware, "cpu_flags", lambda f=flags: f)
        cfg = make_config("halfcheetah", overrides={"device": "cpu"})
        assert (cfg.planner.precision, cfg.model.precision) == (expected, expected)
        path = tmp_path / "config.yaml"
        path.write_text(OmegaConf.to_yaml(cfg))
        assert f"precision: {expected}" in path.read_text()  # config.yaml says what the run used
        other = AMX if expected == "fp32" else OLD
        monkeypatch.setattr(hardware, "cpu_flags", lambda o=other: o)
        assert load_config(str(path)).planner.precision == expected  # a resumed run keeps it on any machine
        monkeypatch.setattr(hardware, "cpu_flags", lambda f=flags: f)
    # fp32 stays the precise path when asked for; a hand-written auto is resolved on load
    assert make_config("reacher", overrides={"planner.precision": "fp32"}).planner.precision == "fp32"
    with pytest.raises(ConfigError, match="model.precision must be one of auto, fp32, bf16"):
        make_config("reacher", overrides={"model.precision": "fp16"})
    stored = OmegaConf.to_container(make_config("reacher", overrides={"device": "cpu"}))
    stored["planner"]["precision"] = "auto"
    del stored["model"]["precision"]  # a run from before the key existed trained in fp32
    path.write_text(OmegaConf.to_yaml(OmegaConf.create(stored)))
    monkeypatch.setattr(hardware, "cpu_flags", lambda: ZEN4)
    back = load_config(str(path))
    assert (back.planner.precision, back.model.precision) == ("bf16", "fp32")


def _train(precision: str, epochs: int = 8):
    import envs
    from pets.builder import make_trainer
    from pets.data.rollout import collect_random
    from pets.models import make_model

    spec = envs.get("halfcheetah")
    cfg = make_config("halfcheetah", overrides={"device": "cpu", "model.precision": precision})
    cfg.model.ensemble_size, cfg.model.num_elites, cfg.model.max_epochs = 5, 5, epochs
    obs, act, nxt = (torch.as_tensor(x) for x in collect_random(spec, 1500, 0))
    torch.manual_seed(0)
    model = make_model(cfg, spec, torch.device("cpu"))
    with emulated_bf16_warning() if precision == "bf16" else contextlib.nullcontext():
        trainer = make_trainer(cfg, model)
    assert trainer.precision == precision
    trainer.patience = epochs + 1  # a fixed budget: no early stop
    result = trainer.train(obs, act, nxt, torch.Generator().manual_seed(1))
    return result, model


def test_bf16_training_reaches_the_fp32_holdout_error_with_fp32_weights(single_thread):
    r32, m32 = _train("fp32")
    r16, m16 = _train("bf16")
    assert r32.epochs == r16.epochs == 8
    assert all(p.dtype == torch.float32 for p in m16.parameters())  # fp32 master weights
    assert math.isfinite(r16.val_loss) and r16.val_loss < 0.9 * r16.initial_val_loss  # it learnt
    w32, w16 = m32.member_parameters()[0], m16.member_parameters()[0]
    assert not torch.equal(w32, w16)  # bf16 really ran
    print(f"holdout error fp32 {r32.val_loss:.5f}, bf16 {r16.val_loss:.5f}")
    assert abs(r16.val_loss / r32.val_loss - 1) < BF16_TRAIN_RELATIVE


def test_bf16_training_is_reproducible(single_thread):
    a, ma = _train("bf16", epochs=2)
    b, mb = _train("bf16", epochs=2)
    assert a.val_loss == b.val_loss
    assert all(torch.equal(x, y) for x, y in zip(ma.parameters(), mb.parameters()))


def test_a_run_on_the_default_precision_repeats_its_metrics(tmp_path):
    """Same seed, same machine -> the same metrics, on the default (auto: bf16 here when native)."""
    import csv

    import run_pets
    from pets.runs import rundir
    from tests.test_cli import TINY

    metrics = []
    for name in ("a", "b"):
        out = tmp_path / name
        assert run_pets.main(["--env", "halfcheetah", "--trials", "2", "--out", str(out), *TINY]) == 0
        assert load_config(str(out / "config.yaml")).planner.precision == hardware.resolve_precision("auto", "auto")
        with open(out / "metrics.csv") as f:
            rows = list(csv.DictReader(f))
        metrics.append([{k: v for k, v in r.items() if k not in rundir.TIMING_COLUMNS} for r in rows])
    assert metrics[0] == metrics[1] and len(metrics[0]) == 2


def test_bench_compare_marks_or_adds_the_default_row_and_names_the_isa(monkeypatch, capsys):
    from pets import bench

    labels = [label for label, _ in bench.COMPARE_ROWS]
    rows = bench.compare_rows(make_config("halfcheetah", overrides={"planner.precision": "bf16"}))
    assert [label for label, _ in rows] == [
        *(f"default: {label}" if label == "cem bf16 eager" else label for label in labels),
        "cem bf16 eager relu",  # the default path with the other activation, last
    ]  # marked, not timed twice
    rows = bench.compare_rows(make_config("hopper", overrides={"planner.precision": "bf16", "planner.name": "mppi"}))
    assert rows[-2] == ("default: mppi bf16 eager", {"name": "mppi", "precision": "bf16", "compile": False})
    assert rows[-1][1] == {"name": "mppi", "precision": "bf16", "compile": False, "activation": "relu"}
    assert len(rows) == len(labels) + 2
    relu = make_config("hopper", overrides={"model.activation": "relu"})
    assert bench.compare_rows(relu)[-1][1]["activation"] == "silu"
    assert bench._row_config(relu, bench.compare_rows(relu)[-1][1]).model.activation == "silu"
    # where bf16 is emulated (~35x slower, minutes a step) the bf16 rows are left out, unless asked for
    rows = bench.compare_rows(make_config("halfcheetah", overrides={"planner.precision": "fp32"}), bf16=False)
    assert [label for label, _ in rows] == [
        "default: cem fp32 eager",
        "cem fp32 compiled",
        "icem fp32 eager",
        "mppi fp32 eager",
        "cem fp32 eager relu",
    ]
    rows = bench.compare_rows(make_config("halfcheetah", overrides={"planner.precision": "bf16"}), bf16=False)
    assert [label for label, planner in rows if planner["precision"] == "bf16"] == [
        "default: cem bf16 eager",
        "cem bf16 eager relu",
    ]
    monkeypatch.setattr(hardware, "cpu_flags", lambda: OLD)
    assert not bench.bf16_is_native(torch.device("cpu")) and bench.bf16_is_native(torch.device("cuda"))
    monkeypatch.setattr(hardware, "cpu_flags", lambda: ZEN4)
    assert bench.bf16_is_native(torch.device("cpu"))
    monkeypatch.setattr(hardware, "cpu_flags", lambda: AMX)
    monkeypatch.setattr(bench, "benchmark", lambda cfg, repeats: (_ for _ in ()).throw(SystemExit(0)))
    with pytest.raises(SystemExit):
        bench.main(["--env", "hopper", "threads=1"])
    assert "CPU bf16 ISA: AMX;" in capsys.readouterr().out


def test_the_fused_bf16_planner_path_is_deterministic(monkeypatch):
    """The research config's bf16 path (dynamics.fused, forced here with MIN_ROWS = 0): the same generator
    seed gives bit-identical returns, call after call and evaluator after evaluator."""
    import envs
    from dynamics import fused
    from dynamics.heads import DeltaHead
    from dynamics.model import DynamicsModel
    from dynamics.networks import GaussianEnsemble
    from pets.planning.propagation import TrajectoryEvaluator

    if not fused._AVAILABLE:
        pytest.skip("oneDNN has no fused bf16 linear on this CPU or build (AVX2-only x86: the batched bf16 path runs)")
    monkeypatch.setattr(fused, "MIN_ROWS", 0)
    calls = []
    real = fused.fused_member_mlp
    monkeypatch.setattr(fused, "fused_member_mlp", lambda *a: calls.append(1) or real(*a))
    spec = envs.get("halfcheetah")
    head = DeltaHead(spec.layout, spec.act_dim)
    torch.manual_seed(0)
    ens = GaussianEnsemble(head.input_dim, head.target_dim, ensemble_size=5, hidden_size=64, num_layers=3)
    obs0 = torch.randn(spec.obs_dim) * 0.1
    actions = torch.rand(40, 6, spec.act_dim, generator=torch.Generator().manual_seed(1)) * 2 - 1
    returns = []
    for _ in range(2):
        ev = TrajectoryEvaluator(DynamicsModel(head, ens), spec.reward, spec.terminated, particles=5, precision="bf16")
        returns += [ev(obs0, actions, torch.Generator().manual_seed(2)) for _ in range(2)]
    assert calls and all(torch.equal(r, returns[0]) for r in returns)


def test_bench_layers_says_why_where_oneDNN_has_no_fused_bf16_linear(monkeypatch, capsys):
    from dynamics import fused
    from pets import bench_layers

    monkeypatch.setattr(fused, "_AVAILABLE", False)
    with pytest.raises(SystemExit) as stop:
        bench_layers.main(["--rows", "8", "--repeats", "1"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "oneDNN has no fused bf16 linear on this CPU" in err
