"""The compiled training step (``model.compile``, ``pets.learning.compiled.CompiledStep``) against the eager reference.

Same data, seeds and batches on both paths. In fp32 the two agree to float rounding (the compiled step is the
same arithmetic in another order); under bf16 autocast the roundings of the two paths differ and drift apart over
the steps, so bf16 is held to the tolerance of bf16 training itself (``tests/test_precision.py``: the holdout
error within 1 % of fp32's). Most tests compile with ``aot_eager`` (graph capture and AOT autograd, no C++ build);
one compiles with inductor, the path runs use.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import pytest
import torch
from omegaconf import OmegaConf
from torch._dynamo.testing import CompileCounterWithBackend

import envs
from pets import builder
from pets.config import ConfigError, load_config, make_config
from pets.data.rollout import collect_random
from pets.learning import trainer as trainer_mod
from pets.learning.trainer import ModelTrainer
from pets.models import make_model
from pets.runs.hardware import AUTO_COMPILE_MIN_TRIALS, resolve_model_compile

pytestmark = pytest.mark.usefixtures("single_thread")

#: fp32, one epoch per trial: compiled and eager holdout errors agree to this (relative). Over more steps the two
#: float orders drift apart as any two do (Reacher / gem, fp32, 630 rows: weights 1e-6 apart after 30 steps, 7e-3
#: after 60; torch's fused Adam against its loop drifts alike), so longer runs are held to outcome tolerances.
FP32_RELATIVE = 1e-4
#: bf16: the tolerance of bf16 training against fp32 (tests/test_precision.py::BF16_TRAIN_RELATIVE).
BF16_RELATIVE = 0.01


@pytest.fixture(scope="module")
def reacher_data() -> tuple[torch.Tensor, ...]:
    """700 random Reacher transitions (630 training rows: 19 full batches of 32 and a partial one) and 200 to test."""
    spec = envs.get("reacher")
    train = tuple(torch.as_tensor(x) for x in collect_random(spec, 700, 0))
    test = tuple(torch.as_tensor(x) for x in collect_random(spec, 200, 5))
    return train + test


def train_pair(
    data: tuple[torch.Tensor, ...],
    precision: str,
    backend: str | Callable,
    overrides: dict[str, str] | None = None,
    paths: tuple[bool, ...] = (False, True),
) -> list[tuple[ModelTrainer, list, torch.Tensor]]:
    """Eager and compiled trainers (``paths``: compiled or not) from the same initial weights, each trained twice
    (two trials) on ``data``: (trainer, [TrainResult, TrainResult], predictions on the test transitions)."""
    small = {"model.max_epochs": "3", "model.num_layers": "2", "model.hidden_size": "64"}  # compiles faster
    cfg = make_config("reacher", "gem", "fast", {**small, **(overrides or {})})
    spec = envs.get("reacher")
    out = []
    for compiled in paths:
        torch.manual_seed(0)
        model = make_model(cfg, spec, torch.device("cpu"))
        tr = builder.make_trainer(cfg, model)
        tr.precision, tr.compile, tr.compile_backend = precision, compiled, backend
        results = [tr.train(*data[:3], torch.Generator().manual_seed(seed)) for seed in (1, 2)]
        out.append((tr, results, model.predict(data[3], data[4])))
    return out


@pytest.fixture(scope="module")
def fp32_predictions(reacher_data) -> torch.Tensor:
    """The eager fp32 trainer's predictions on the test transitions (same weights, data and batches)."""
    ((_, _, predictions),) = train_pair(reacher_data, "fp32", "aot_eager", paths=(False,))
    return predictions


def assert_within_bf16(
    r_e: list, r_c: list, p_e: torch.Tensor, p_c: torch.Tensor, p_32: torch.Tensor, truth: torch.Tensor
) -> None:
    """The compiled bf16 step within the tolerance of bf16 training itself: its holdout errors within
    :data:`BF16_RELATIVE` of the eager step's, and its predictions near the fp32 model's: within 5 % of the model's
    own error (``truth``: the test transitions' next states), or no further than twice the eager bf16 model's are
    (two bf16 roundings of the same training drift apart by about as much as either drifts from fp32: on an AVX2 CPU
    that emulates bf16, aot_eager's predictions were 1.33x and inductor's 0.94x the eager distance from fp32, 4.6 %
    of the error, while aot_eager's and eager's differed by 6 %). A wrong step is far outside either."""
    for a, b in zip(r_e, r_c):
        assert b.val_loss == pytest.approx(a.val_loss, rel=BF16_RELATIVE)
    err = (p_32 - truth).abs().mean()
    assert (p_c - p_32).abs().mean() < max(0.05 * err, 2 * (p_e - p_32).abs().mean())


def test_compiled_fp32_matches_eager(reacher_data, monkeypatch) -> None:
    """fp32: the same holdout errors, epochs, elites and predictions as the eager step, over two trials of one
    epoch, with the
    gathers split into several chunks (GATHER_BATCHES) and a partial last batch (run eagerly)."""
    monkeypatch.setattr(trainer_mod, "GATHER_BATCHES", 4)
    backend = CompileCounterWithBackend("aot_eager")
    (eager, r_e, p_e), (comp, r_c, p_c) = train_pair(reacher_data, "fp32", backend, {"model.max_epochs": "1"})
    assert comp._compiled is not None and not comp._compile_failed
    assert backend.frame_count == 1  # compiled once for both trials (train calls)
    for a, b in zip(r_e, r_c):
        assert a.epochs == b.epochs
        assert b.val_loss == pytest.approx(a.val_loss, rel=FP32_RELATIVE)
        assert b.initial_val_loss == pytest.approx(a.initial_val_loss, rel=FP32_RELATIVE)
    assert torch.equal(eager.model.elites, comp.model.elites)
    assert torch.allclose(p_c, p_e, rtol=1e-4, atol=1e-4)
    # The compiled step keeps torch Adam's state: one step per minibatch (full ones compiled, partial ones eager).
    steps = sum(r.epochs for r in r_c) * 20
    for p in comp.model.parameters():
        assert float(comp.optimizer.state[p]["step"]) == steps


def test_compiled_bf16_within_the_bf16_tolerance(reacher_data, fp32_predictions) -> None:
    """bf16 autocast: the holdout errors and predictions within the tolerance bf16 training has against fp32."""
    (_, r_e, p_e), (_, r_c, p_c) = train_pair(reacher_data, "bf16", "aot_eager")
    assert_within_bf16(r_e, r_c, p_e, p_c, fp32_predictions, reacher_data[5])


def test_inductor_step_within_tolerance(reacher_data, fp32_predictions) -> None:
    """The path runs take (inductor, bf16 on this project's CPUs): within the bf16 tolerance of the eager step,
    compiled once for both trials."""
    (_, r_e, p_e), (comp, r_c, p_c) = train_pair(reacher_data, "bf16", "inductor")
    assert not comp._compile_failed
    assert_within_bf16(r_e, r_c, p_e, p_c, fp32_predictions, reacher_data[5])


def test_a_failing_compile_warns_and_trains_eagerly(reacher_data) -> None:
    """A backend that cannot compile: one warning, then the eager step, bit for bit the eager result."""

    def broken(gm, inputs):
        raise RuntimeError("no C++ compiler")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        (_, r_e, p_e), (comp, r_c, p_c) = train_pair(reacher_data, "fp32", broken)
    assert comp._compile_failed
    assert sum("torch.compile of the training step failed" in str(w.message) for w in caught) == 1
    assert [r.val_loss for r in r_c] == [r.val_loss for r in r_e]
    assert torch.equal(p_c, p_e)


def test_checkpointed_optimizer_moves_between_paths(reacher_data) -> None:
    """The optimiser state a compiled trainer saves loads into an eager one, and the eager one trains on."""
    (_, _, _), (comp, _, _) = train_pair(reacher_data, "fp32", "aot_eager", {"model.max_epochs": "1"})
    state = comp.state_dict()
    eager = ModelTrainer(comp.model, batch_size=32, max_epochs=1, compile=False)
    eager.load_state_dict(state)
    eager.train(*reacher_data[:3], torch.Generator().manual_seed(3))
    p = next(comp.model.parameters())
    assert float(eager.optimizer.state[p]["step"]) == float(state["optimizer"]["state"][0]["step"]) + 20


def test_model_compile_key(real_auto_compile) -> None:
    """``model.compile``: off at the research preset, ``auto`` at the fast preset (resolved to a bool when the config
    is made), a bool or auto (anything else is a ConfigError), passed to the trainer."""
    assert make_config("reacher", "gem").model.compile is False
    cfg = make_config("reacher", "gem", "fast", {"model.compile": "true"})
    assert cfg.model.compile is True
    model = make_model(cfg, envs.get("reacher"), torch.device("cpu"))
    assert builder.make_trainer(cfg, model).compile is True
    for preset, overrides in (("fast", {}), ("research", {"model.compile": "auto"})):
        auto = make_config("reacher", "gem", preset, overrides)
        assert auto.model.compile is resolve_model_compile(None, auto.model.precision, auto.device, auto.trials)
    assert make_config("reacher", "gem", "fast", {"trials": "9"}).model.compile is False  # a short run: eager
    with pytest.raises(ConfigError, match="model.compile"):
        make_config("reacher", "gem", "fast", {"model.compile": "maybe"})
    with pytest.raises(ValueError, match="compile must be a bool"):
        ModelTrainer(model, compile="yes")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("flags", "precision", "device", "trials", "expected"),
    [
        ({"avx512_bf16"}, "bf16", "cpu", AUTO_COMPILE_MIN_TRIALS, True),  # measured ~2x (docs/performance.md)
        ({"amx_bf16", "avx512_bf16"}, "bf16", "cpu", 300, True),
        ({"avx512_bf16"}, "bf16", "cpu", AUTO_COMPILE_MIN_TRIALS - 1, False),  # too short to pay back
        ({"avx512_bf16"}, "fp32", "cpu", 100, False),  # fp32 training: not measured to pay
        (set(), "fp32", "cpu", 100, False),  # no native bf16
        ({"avx512_bf16"}, "fp32", "cuda", 100, False),  # CUDA: not measured
    ],
)
def test_auto_model_compile_where_measured(flags, precision, device, trials, expected, real_auto_compile) -> None:
    assert resolve_model_compile(None, precision, device, trials, frozenset(flags)) is expected
    for explicit in (True, False):
        assert resolve_model_compile(explicit, precision, device, trials, frozenset(flags)) is explicit


def test_a_resolved_config_yaml_stores_a_bool(tmp_path, real_auto_compile) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(OmegaConf.to_yaml(make_config("reacher", "gem", "fast")))
    assert OmegaConf.load(path).model.compile in (True, False)
    assert load_config(str(path)).model.compile == make_config("reacher", "gem", "fast").model.compile


def test_a_config_yaml_without_model_compile_loads_as_eager(tmp_path) -> None:
    stored = OmegaConf.to_container(make_config("reacher", "gem", "fast"))
    del stored["model"]["compile"]
    path = tmp_path / "config.yaml"
    path.write_text(OmegaConf.to_yaml(stored))
    assert load_config(str(path)).model.compile is False
