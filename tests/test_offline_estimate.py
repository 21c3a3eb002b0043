"""pets.compare offline --estimate (pets.experiments.offline_estimate): the data sets and trainings still to do,
counted from the sweep (against hand arithmetic, the real sweep's data file and the architectures its runs record
having searched), the CPU-hours from per-step figures measured on this machine; nothing is run or written."""

from __future__ import annotations

import pytest

from pets.config import make_config
from pets.data.datasets import load_dataset
from pets.experiments import offline_estimate as est
from pets.experiments.cli import main
from pets.runs import rundir

SWEEP = ["offline", "--envs", "invertedpendulum", "--models", "delta", "--seeds", "0,1", "--protocol", "paper"]
SWEEP += ["--policy", "sac:200", "--test-episodes", "2", "--max-steps", "30", "--starts", "20", "--horizons", "1,5"]
SWEEP += ["--quiet", "model.iterations=20"]


def test_the_projection_multiplies_the_measured_steps_by_the_runs_architectures_and_data():
    cfgs = {f"ant-{m}-s{s}": make_config("ant", m, "research", {"model.iterations": 10_000}) for m in ("delta", "gem")
            for s in (0, 1)}  # fmt: skip
    archs = {name: ((512, 1), (512, 2)) for name in cfgs}
    archs["ant-gem-s1"] = ((200, 4),)  # not measured: the arm's first run to train gives its architectures
    grads = {(512, 1): 0.01, (512, 2): 0.02}
    seen = []

    def measure_grad(cfg):
        seen.append((cfg.head, cfg.model.hidden_size, cfg.model.num_layers))
        return grads[cfg.model.hidden_size, cfg.model.num_layers] * (2 if cfg.head == "gem" else 1)

    data_jobs = [("ant data 0", None, ("ant", [("t.npz", "sac:1000", 5, 0), ("e.npz", "sb3:a.zip", 2, 1)], 300, 0, 1))]
    text = est.offline_estimate(
        cfgs, {"ant-delta-s1", "ant-gem-s0", "ant-gem-s1"}, archs.__getitem__, data_jobs, workers=2,
        measure_grad=measure_grad, measure_data=lambda env, kind, threads: (0.036, 0.0018),
    )  # fmt: skip
    assert seen == [("delta", 512, 1), ("delta", 512, 2), ("gem", 512, 1), ("gem", 512, 2)]
    lines = text.splitlines()
    # data: 1,000 SAC steps x 0.036 s + 2 test episodes x 300 steps x 0.0018 s = 37.08 s = 0.0103 h
    assert lines[2] == "| ant data 0 | 1,000 (0.036 s a step) | 600 (0.0018 s a step) | 0.0103 |"
    # delta: one run (s0 is trained), 10,000 x (0.01 + 0.02) s = 300 s; gem: two runs x 10,000 x 0.06 s = 1,200 s
    assert lines[6] == "| ant-delta | 1 | 20,000 | 512x1 (0.01 s), 512x2 (0.02 s) | 0.0833 |"
    assert lines[7] == "| ant-gem | 2 | 40,000 | 512x1 (0.02 s), 512x2 (0.04 s) | 0.333 |"
    assert lines[9].startswith(
        "1 data set to make and 3 runs to train, about 0.427 CPU-hours (0.219 h of wall time"
    )  # 0.0103 + 0.417 / 2
    nothing = est.offline_estimate(cfgs, set(), archs.__getitem__, [], None, measure_grad, lambda *a: (0.0, 0.0))
    assert nothing.startswith("nothing to train or collect")
    epochs = {"ant-delta-s0": make_config("ant", "delta", "research", {"model.iterations": 0})}
    text = est.offline_estimate(epochs, set(epochs), archs.__getitem__, [], None, measure_grad)
    assert "| ant-delta | 1 | by epochs | - | not projected (epochs) |" in text and "wall time" not in text
    assert "training by epochs not included" in text


def test_estimate_before_a_real_sweep_counts_its_data_and_searched_architectures_and_writes_nothing(
    tmp_path, capsys, monkeypatch
):
    out = tmp_path / "sweep"
    assert main([*SWEEP, "--out", str(out), "--estimate"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert not out.exists()
    data = lines[2].split(" | ")
    assert data[0] == "| invertedpendulum data 0" and data[1].startswith("200 (") and data[2].startswith("60 (")
    sac_s, rolled_s = (float(cell.split("(")[1].split(" s")[0]) for cell in data[1:3])
    assert sac_s > rolled_s > 0  # a SAC step trains; a rolled one only acts
    run = lines[6].split(" | ")
    assert run[:3] == ["| invertedpendulum-delta", "2", "120"]  # 2 runs x 3 architectures x 20 iterations
    assert [a.split(" (")[0] for a in run[3].split(", ")] == ["100x1", "100x2", "100x3"]
    assert main([*SWEEP, "--out", str(out)]) == 0  # the sweep, for real
    capsys.readouterr()
    arrays = load_dataset(out / "data" / "invertedpendulum-test.npz")
    assert int(arrays["lengths"].sum()) <= 60 and len(arrays["lengths"]) == 2  # episodes that end early cost less
    searched = rundir.load_checkpoint(out / "runs" / "invertedpendulum-delta-s0")["offline"]["search"]
    assert [f"{c['hidden_size']}x{c['num_layers']}" for c in searched] == ["100x1", "100x2", "100x3"]
    assert main([*SWEEP, "--out", str(out), "--estimate"]) == 0
    assert capsys.readouterr().out.startswith("nothing to train or collect")
    (out / "runs" / "invertedpendulum-delta-s1" / "config.yaml").unlink()  # a run to train again, its data there
    monkeypatch.setattr(est, "_grad_seconds", lambda cfg: 0.001)
    with pytest.raises(SystemExit) as exit_info:  # another config: refused, as the sweep itself refuses it
        main([*SWEEP, "--out", str(out), "--estimate", "model.iterations=30"])
    assert exit_info.value.code == 2 and "model.iterations: 20 != 30" in capsys.readouterr().err
    assert main([*SWEEP, "--out", str(out), "--estimate"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| env, arm") and lines[2].startswith("| invertedpendulum-delta | 1 | 60 |")
    assert lines[4].startswith("0 data sets to make and 1 run to train")


def test_without_out_every_data_set_and_run_is_to_do_and_a_fixed_architecture_is_the_only_one(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setattr(est, "_grad_seconds", lambda cfg: 0.001)
    monkeypatch.setattr(est, "_data_seconds", lambda env, kind, threads: (0.01, 0.001))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "invertedpendulum-train.npz").write_text("not a data set")  # not looked at
    assert main([*SWEEP, "--estimate", "model.hidden_size=64", "model.num_layers=2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[2] == "| invertedpendulum data 0 | 200 (0.01 s a step) | 60 (0.001 s a step) | 0.000572 |"
    assert lines[6].startswith("| invertedpendulum-delta | 2 | 40 | 64x2 (0.001 s) |")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    assert "planning" not in lines[-1]  # none asked for
    assert main([*SWEEP, "--estimate", "--closedloop", "--planners", "cem"]) == 0
    assert "nor the open- and closed-loop planning this sweep asks for" in capsys.readouterr().out
    assert main([*SWEEP, "--policy", "existing", "--estimate"]) == 0  # the user's files: nothing to collect
    assert capsys.readouterr().out.startswith("| env, arm")


def test_a_stopped_sac_collection_counts_the_steps_its_checkpoint_leaves(tmp_path, monkeypatch, capsys):
    import envs
    from pets.data.sb3 import sac_checkpoint_path, sac_steps_done, train_sac
    from pets.experiments.offline_data import collect_seeds, data_paths

    monkeypatch.setattr(est, "_grad_seconds", lambda cfg: 0.001)
    monkeypatch.setattr(est, "_data_seconds", lambda env, kind, threads: (0.01, 0.001))
    out = tmp_path / "sweep"
    train_path = data_paths(out / "data", "invertedpendulum")[0]
    train_path.parent.mkdir(parents=True)
    checkpoint = sac_checkpoint_path(train_path)
    # the sweep's own SAC collection of this data set, its checkpoint at 100 of its 200 steps (the one a stop leaves)
    train_sac(envs.get("invertedpendulum"), 200, seed=collect_seeds(0)[0], max_steps=30, checkpoint=checkpoint,
              checkpoint_every=100)  # fmt: skip
    assert sac_steps_done(train_path) == 100 and sac_steps_done(tmp_path / "none.npz") == 0
    assert main([*SWEEP, "--out", str(out), "--estimate"]) == 0
    assert capsys.readouterr().out.splitlines()[2].startswith("| invertedpendulum data 0 | 100 (0.01 s a step) |")
    checkpoint.write_bytes(b"not a checkpoint")  # unreadable: the collection starts over, all of it counts
    assert main([*SWEEP, "--out", str(out), "--estimate"]) == 0
    assert capsys.readouterr().out.splitlines()[2].startswith("| invertedpendulum data 0 | 200 (0.01 s a step) |")
