"""Limits before memory (issue 55): every size key is bounded and the memory a config needs is estimated before
anything is allocated; what this machine cannot hold is one line and exit 2 within seconds, in run_pets.py,
pets.openloop and the Python API, and a run refused that way leaves no directory behind."""

from __future__ import annotations

import re
import sys
import time

import pytest

import pets
from pets.config import ConfigError
from pets.limits import SIZE_BOUNDS
from tests import warm
from tests.test_cli import ROOT, TINY, cli, error_lines

#: (env, override, what the one line says): the values of issue 55 and two the estimate refuses (terabytes).
TOO_BIG = [
    ("halfcheetah", "planner.population=1000000000000", "planner.population must be <= 10,000,000"),
    ("halfcheetah", "episode_length=100000000000000000000", "episode_length must be <= 10,000,000"),
    ("halfcheetah", "model.hidden_size=100000000", "model.hidden_size must be <= 1,000,000"),
    ("halfcheetah", "planner.horizon=1000000000", "planner.horizon must be <= 100,000"),
    ("halfcheetah", "seed_steps=10000000000000", "seed_steps must be <= 1,000,000,000"),
    ("halfcheetah", "model.hidden_size=100000", "lower model.hidden_size, model.num_layers or model.ensemble_size"),
    ("humanoid", "seed_steps=999999999", "lower seed_steps, trials or episode_length"),
    ("invertedpendulum", "seed=4294967296", "seed must be <= 4,294,967,295 (2**32 - 1)"),  # was a traceback
]


@pytest.mark.parametrize(("env", "override", "fragment"), TOO_BIG)
def test_a_config_too_big_is_one_line_within_seconds_and_leaves_no_directory(tmp_path, env, override, fragment):
    start = time.monotonic()
    proc = cli("--env", env, "--model", "gem", "--out", tmp_path / "run", override, check=False, timeout=120)
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], proc.stderr
    assert time.monotonic() - start < 60 and not (tmp_path / "run").exists()


def test_an_error_found_when_the_run_is_built_leaves_no_directory_holding_only_the_lock(tmp_path):
    feedback = ["planner.candidates=feedback", "planner.feedback.features=[0,99]", "planner.replan_every=1"]
    proc = cli("--env", "halfcheetah", "--out", tmp_path / "run", "--preset", "fast", *feedback, check=False)
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and "features must be distinct" in lines[0], proc.stderr
    assert not (tmp_path / "run").exists()
    mine = tmp_path / "mine"  # a folder of the user's: kept, only the lock goes
    mine.mkdir()
    cli("--env", "halfcheetah", "--out", mine, "--preset", "fast", *feedback, check=False)
    assert mine.is_dir() and list(mine.iterdir()) == []


def test_pets_openloop_refuses_a_planner_too_big_in_one_line(tmp_path):
    run = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--out", run, *TINY)
    for args, fragment in (
        (["--steps", "100000000000000000000"], "--steps must be <= 100,000"),
        (["planner.population=100000000000"], "planner.population must be <= 10,000,000"),
        (["planner.population=5000000", "planner.particles=1000"], "lower planner.population, planner.particles"),
    ):
        proc = warm.run(
            [sys.executable, "-m", "pets.openloop", "--run", str(run), "--quiet", *args],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], proc.stderr


def test_train_oracle_and_bench_refuse_what_this_machine_cannot_hold_in_one_line(tmp_path):
    """pets.train (its architectures), pets.oracle (population x horizon) and pets.bench were a 40-line traceback
    from the allocator; pets.bench's --device cuda without one and an unwritable --json (after the timing) too.
    pets.train leaves no --out behind."""
    from tests.processes import collect_random

    data = collect_random(tmp_path / "ip.npz", 1)
    cases = [
        (
            "pets.train",
            ["--data", data, "--model", "delta", "--out", tmp_path / "t", "model.hidden_size=200000"],
            "lower model.hidden_size, model.num_layers or model.ensemble_size",
        ),
        (
            "pets.oracle",
            ["--env", "reacher", "planner.population=10000000", "planner.horizon=100000"],
            "lower planner.population, planner.particles",
        ),
        (
            "pets.bench",
            ["--env", "reacher", "--repeats", "1", "planner.population=10000000", "planner.particles=1000"],
            "lower planner.population, planner.particles",
        ),
        ("pets.bench", ["--env", "reacher", "--preset", "fast", "--json", "/proc/b.json"], "cannot write --json"),
    ]
    if not __import__("torch").cuda.is_available():
        cases.append(("pets.bench", ["--env", "reacher", "--device", "cuda"], "torch sees no CUDA device"))
    for module, args, fragment in cases:
        proc = warm.run([sys.executable, "-m", module, *map(str, args)], cwd=ROOT, capture_output=True, text=True,
                        timeout=120)  # fmt: skip
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert proc.returncode == 2 and len(lines) == 1 and fragment in lines[0], (module, proc.stderr[-2000:])
    assert not (tmp_path / "t").exists()


def test_the_api_refuses_a_config_too_big_before_allocating():
    # device=cpu: with auto on a CUDA machine the model is on the GPU, and the refusal names the GPU's memory
    with pytest.raises(ConfigError, match="needs about .* GB of host memory"):
        pets.PETS("halfcheetah", model="gem", device="cpu", **{"model.hidden_size": 100_000})
    with pytest.raises(ConfigError, match="planner.population must be <= "):
        pets.PETS("halfcheetah", **{"planner.population": 10**12})


def test_every_bound_is_above_what_the_presets_use():
    from pets.config import make_config

    for preset in ("research", "fast"):
        cfg = make_config("humanoid", "gem", preset)
        for key, most in SIZE_BOUNDS.items():
            value = cfg
            for part in key.split("."):
                value = value[part]
            assert value is None or value <= most // 100, (key, value)


def test_pets_compare_refuses_runs_that_do_not_fit_at_once_before_any_starts(tmp_path, monkeypatch, capsys):
    """pets.compare online checks the memory of the CPU runs to do before it starts one (exit 2, one line, no --out),
    --workers K of them at once: a sweep whose runs fit one by one but not K together is refused too. --device cpu:
    a CUDA run checks the GPU's memory itself as it starts (the sweep's process reads no GPU)."""
    import envs
    from pets.config import make_config
    from pets.experiments.cli import main
    from pets.limits import memory_needs

    def no_run(*args, **kwargs):
        raise AssertionError("a run would start: the memory was not checked before")

    monkeypatch.setattr("pets.experiments.online.open_backend", no_run)
    args = ["online", "--envs", "halfcheetah", "--models", "delta,gem", "--seeds", "0", "--trials", "2", "--quiet"]
    args += ["--preset", "research", "--device", "cpu"]
    with pytest.raises(SystemExit) as info:
        main([*args, "--out", str(tmp_path / "big"), "model.hidden_size=100000"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and len(err.strip().splitlines()) == 1, err
    assert re.search(r"halfcheetah-(delta|gem)-s0: this config needs about", err) and not (tmp_path / "big").exists()

    spec = envs.get("halfcheetah")
    cfg = make_config("halfcheetah", "gem", "research", {"trials": 2})
    one = sum(n.bytes for n in memory_needs(cfg, spec.obs_dim, spec.act_dim, spec.episode_length))
    monkeypatch.setattr("pets.limits.available_bytes", lambda device: 1.5 * one)  # room for one run, not two
    two = ["online", "--envs", "halfcheetah", "--models", "gem", "--seeds", "0,1", "--trials", "2", "--quiet"]
    two += ["--device", "cpu"]
    with pytest.raises(SystemExit) as info:
        main([*two, "--preset", "research", "--workers", "2", "--out", str(tmp_path / "two")])
    err = capsys.readouterr().err
    assert info.value.code == 2 and len(err.strip().splitlines()) == 1, err
    assert "with the 1 other run(s) at once (--workers)" in err and err.rstrip().endswith("or --workers"), err
    assert not (tmp_path / "two").exists()
    with pytest.raises(AssertionError, match="a run would start"):  # one at a time fits: the sweep would start
        main([*two, "--preset", "research", "--workers", "1", "--out", str(tmp_path / "one")])


def test_on_a_cuda_device_the_gpu_parts_are_checked_against_the_gpus_free_memory_the_rest_against_the_hosts(
    monkeypatch,
):
    """The CUDA branch on a machine without one: torch.cuda reports a GPU with the free memory the test sets. The
    model, its training data and the planner must fit in the GPU's free memory, the numpy replay buffer in the
    host's; each refusal names the memory that is short. The training data (the buffer's tensors and the normalised
    inputs, on the GPU) was counted in host memory, so a GPU too small for it was not refused."""
    import torch

    import envs
    from pets.builder import check_memory
    from pets.config import make_config
    from pets.limits import GB, KEYS, available_bytes, memory_needs

    spec = envs.get("halfcheetah")
    cfg = {on: make_config("halfcheetah", "gem", "research", {"seed_steps": 50_000_000, "device": on}) for on in
           ("cuda", "cpu")}  # fmt: skip
    needs = memory_needs(cfg["cuda"], spec.obs_dim, spec.act_dim, spec.episode_length)
    host, gpu = [n for n in needs if n.host], [n for n in needs if not n.host]
    on_host, on_gpu = sum(n.bytes for n in host), sum(n.bytes for n in gpu)
    assert [n.part for n in host] == ["replay buffer"] and max(gpu, key=lambda n: n.bytes).part == "training data"
    assert on_gpu > on_host > 4 * GB
    free, asked = {"gpu": 0.0, "host": 0.0}, []

    def mem_get_info(device: object = None) -> tuple[int, int]:
        asked.append(device)
        return int(free["gpu"]), int(141 * GB)

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "mem_get_info", mem_get_info)
    monkeypatch.setattr(  # the host's free memory as the test sets it; a GPU's through the real CUDA branch
        "pets.limits.available_bytes", lambda device: free["host"] if device == "cpu" else available_bytes(device)
    )

    def refusal(gpu_free: float, host_free: float, device: str = "cuda") -> str | None:
        free.update(gpu=gpu_free, host=host_free)
        try:
            check_memory(cfg[device], spec)
        except ConfigError as err:
            return str(err)
        return None

    # Each side just fits: refused neither way (before, the training data was added to the host's part).
    assert refusal(1.01 * on_gpu, 1.01 * on_host) is None
    assert asked == [0]  # the current GPU's free memory (device=cuda), read once
    assert refusal(0.5 * on_gpu, 10 * (on_host + on_gpu)) == (
        f"this config needs about {on_gpu / GB:,.1f} GB of GPU memory ({', '.join(map(str, gpu))}), more than the "
        f"{0.5 * on_gpu / GB:,.1f} GB the GPU (cuda) has free; lower {KEYS['training data']}"
    )
    assert refusal(10 * on_gpu, 0.5 * on_host) == (
        f"this config needs about {on_host / GB:,.1f} GB of host memory ({host[0]}), more than the "
        f"{0.5 * on_host / GB:,.1f} GB this machine has free; lower {KEYS['replay buffer']}"
    )
    # On the CPU every part is in host memory: the room that held the buffer alone does not hold them all.
    on_cpu = refusal(0.0, 1.01 * on_host, device="cpu")
    assert on_cpu is not None and on_cpu.startswith(
        f"this config needs about {(on_host + on_gpu) / GB:,.1f} GB of host"
    )
    asked.clear()
    assert available_bytes("cuda:1") == 0.0 and asked == [1]  # cuda:N: that GPU's, not the current one's
