"""The offline protocols: the paper's split, config and hidden-size search, through pets.train."""

import importlib.util
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

import envs
from pets.config import load_config
from pets.data.collect import collect
from pets.data.protocols import PROTOCOLS, get_protocol, split_samples
from pets.learning.offline import offline_config, train_offline
from pets.runs import rundir
from tests.threads import one_thread

ROOT = Path(__file__).resolve().parents[1]


def test_paper_split_sizes_ratio_and_disjointness():
    paper = get_protocol("paper")
    train, val = split_samples(150_000, paper)
    assert (len(train), len(val)) == (100_000, 10_000)
    assert not set(train) & set(val)
    train, val = split_samples(1_100, paper)  # a smaller file keeps the 10:1 ratio
    assert (len(train), len(val)) == (1_000, 100)
    assert np.array_equal(np.sort(np.concatenate([train, val])), np.arange(1_100))
    again = split_samples(1_100, paper)
    assert all(np.array_equal(a, b) for a, b in zip((train, val), again))  # one split per file
    train, val = split_samples(500, get_protocol("pets"))
    assert len(train) == 500 and len(val) == 0
    with pytest.raises(ValueError, match="accepted: pets, paper"):
        get_protocol("nope")


def test_paper_config_is_the_papers_hyperparameters():
    cfg = offline_config("reacher", "delta-det", protocol="paper")
    assert (cfg.model.lr, cfg.model.batch_size, cfg.model.iterations) == (5e-4, 10, 10_000)
    assert cfg.model.bootstrap is False and cfg.model.ensemble_size == cfg.model.num_elites == 5
    single = offline_config("reacher", "delta-det", {"model.ensemble_size": 1, "model.num_elites": 1}, protocol="paper")
    assert single.model.ensemble_size == 1
    assert PROTOCOLS["paper"].architectures("ant") == ((512, 1), (512, 2), (512, 3))
    assert PROTOCOLS["paper"].architectures("hopper") == ((100, 1), (100, 2), (100, 3))


@pytest.fixture(scope="module")
def reacher_arrays():
    return collect(envs.get("reacher"), "random", 12, seed=0, max_steps=25)  # 300 transitions


def test_paper_protocol_searches_the_hidden_layers_and_keeps_the_best(tmp_path, reacher_arrays):
    with one_thread():
        out = train_offline(reacher_arrays, "gem", tmp_path / "run", {"model.iterations": "40"}, protocol="paper")
    meta = rundir.load_checkpoint(out)["offline"]
    assert meta["protocol"] == "paper"
    assert (meta["train_transitions"], meta["validation_transitions"]) == (273, 27)
    search = meta["search"]
    assert [(c["hidden_size"], c["num_layers"]) for c in search] == [(100, 1), (100, 2), (100, 3)]
    best = min(search, key=lambda c: c["val_error"])
    cfg = load_config(str(out / "config.yaml"))
    assert (cfg.model.hidden_size, cfg.model.num_layers) == (best["hidden_size"], best["num_layers"])
    row = rundir.read_metrics(out / "metrics.csv")[0]
    assert row["model_val_loss"] == pytest.approx(best["val_error"])
    assert row["env_steps"] == 273


def test_an_explicit_architecture_turns_the_search_off(tmp_path, reacher_arrays):
    overrides = {"model.iterations": "20", "model.hidden_size": "16", "model.num_layers": "1"}
    with one_thread():
        out = train_offline(reacher_arrays, "delta-det", tmp_path / "run", overrides, protocol="paper")
    assert rundir.load_checkpoint(out)["offline"]["search"] == []
    cfg = load_config(str(out / "config.yaml"))
    assert (cfg.model.hidden_size, cfg.model.num_layers) == (16, 1)
    assert torch.isfinite(torch.tensor(rundir.read_metrics(out / "metrics.csv")[0]["model_val_loss"]))


def test_the_learning_curve_of_the_paper_protocol_for_every_searched_architecture(tmp_path, reacher_arrays):
    """model.curve_every=10 over 40 iterations: learning_curve.csv has steps 0, 10, ..., 40 for each of the 3
    searched architectures; each curve's last point is that candidate's validation error (all 5 members are the
    elites under the paper's protocol), and recording it changes nothing else (same weights, same metrics row)."""
    with one_thread():
        plain = train_offline(reacher_arrays, "gem", tmp_path / "plain", {"model.iterations": "40"}, protocol="paper")
        overrides = {"model.iterations": "40", "model.curve_every": "10"}
        out = train_offline(reacher_arrays, "gem", tmp_path / "curve", overrides, protocol="paper")
    assert not (plain / "learning_curve.csv").exists()
    rows = [line.split(",") for line in (out / "learning_curve.csv").read_text().splitlines()]
    assert rows[0] == ["hidden_size", "num_layers", "step", "holdout_error"]
    search = rundir.load_checkpoint(out)["offline"]["search"]
    for candidate in search:
        points = [
            (int(r[2]), float(r[3])) for r in rows[1:] if (int(r[0]), int(r[1])) == (100, candidate["num_layers"])
        ]
        assert [step for step, _ in points] == [0, 10, 20, 30, 40]
        assert points[-1][1] == pytest.approx(candidate["val_error"], rel=1e-6)
        assert points[-1][1] < points[0][1]  # training lowers the validation error
    assert "curve" not in search[0]  # the curve lives in the CSV, not in the checkpoint's metadata
    metrics = [rundir.read_metrics(run / "metrics.csv")[0] for run in (plain, out)]
    assert metrics[0]["model_val_loss"] == metrics[1]["model_val_loss"]
    weights = [rundir.load_checkpoint(run)["model"] for run in (plain, out)]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])

    script = importlib.util.spec_from_file_location("learning_curves", ROOT / "docs/scripts/learning_curves.py")
    curves = importlib.util.module_from_spec(script)
    script.loader.exec_module(curves)
    assert curves.main([str(tmp_path), "--out", str(tmp_path / "curves.png"), "--csv", str(tmp_path / "c.csv")]) == 0
    kept = (tmp_path / "c.csv").read_text().splitlines()
    assert len(kept) == 1 + 5 and (tmp_path / "curves.png").stat().st_size > 0  # the selected architecture only
    best = min(search, key=lambda c: c["val_error"])
    assert float(kept[-1].split(",")[-1]) == pytest.approx(best["val_error"], rel=1e-6)
    other = tmp_path / "other"  # a second study's runs/ directory: both studies' curves in one figure
    shutil.copytree(out, other / out.name)
    assert (
        curves.main([str(tmp_path), str(other), "--out", str(tmp_path / "both.png"), "--csv", str(tmp_path / "b.csv")])
        == 0
    )
    assert len((tmp_path / "b.csv").read_text().splitlines()) == 1 + 2 * 5
    # the kept points of runs whose directories are gone: an earlier --csv output read back gives the same points
    assert (
        curves.main([str(tmp_path / "c.csv"), "--out", str(tmp_path / "again.png"), "--csv", str(tmp_path / "d.csv")])
        == 0
    )
    assert (tmp_path / "d.csv").read_text() == (tmp_path / "c.csv").read_text()
