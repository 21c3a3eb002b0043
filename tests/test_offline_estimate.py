"""pets.compare offline --estimate (pets.experiments.offline_estimate): the data sets and trainings still to do,
counted from the sweep (against hand arithmetic, the real sweep's data file and the architectures its runs record
having searched), the CPU-hours from per-step figures measured on this machine; nothing is run or written."""

from __future__ import annotations

import json
import shutil

import pytest

from pets.config import make_config
from pets.data.datasets import load_dataset
from pets.experiments import offline_estimate as est
from pets.experiments.cli import main
from pets.runs import rundir
from pets.tools.cli import EXIT_FAILED
from tests.tiny import replacing

SWEEP = ["offline", "--envs", "invertedpendulum", "--models", "delta", "--seeds", "0,1", "--protocol", "paper"]
SWEEP += ["--policy", "sac:200", "--test-episodes", "2", "--max-steps", "30", "--starts", "20", "--horizons", "1,5"]
SWEEP += ["--quiet", "model.iterations=20"]


def test_the_projection_multiplies_the_measured_steps_by_the_runs_architectures_data_and_planning():
    cfgs = {f"ant-{m}-s{s}": make_config("ant", m, "research", {"model.iterations": 10_000}) for m in ("delta", "gem")
            for s in (0, 1)}  # fmt: skip
    archs = {name: ((512, 1), (512, 2)) for name in cfgs}
    archs["ant-gem-s1"] = ((200, 4),)  # not measured for training: the arm's first run to train gives them
    grads = {(512, 1): 0.01, (512, 2): 0.02}
    seen = []

    def measure_grad(cfg):
        seen.append((cfg.head, cfg.model.hidden_size, cfg.model.num_layers))
        return grads[cfg.model.hidden_size, cfg.model.num_layers] * (2 if cfg.head == "gem" else 1)

    def measure_plan(cfg):
        assert cfg.planner.name == "cem" and cfg.planner.horizon in (30, 50)  # closed loop keeps the run's horizon
        return 0.5 if cfg.planner.horizon == 50 else 0.2 if cfg.model.hidden_size == 512 else 0.1

    train = ["train", "eval"]
    pending = {"ant-delta-s1": [*train, "closedloop_cem"], "ant-gem-s0": [*train, "closedloop_cem"],
               "ant-gem-s1": [*train, "closedloop_cem", "openloop_cem"]}  # fmt: skip
    data_jobs = [("ant data 0", None, ("ant", [("t.npz", "sac:1000", 5, 0), ("e.npz", "sb3:a.zip", 2, 1)], 300, 0, 1))]
    measures = est.Measures(measure_grad, lambda env, kind, threads: (0.036, 0.0018), measure_plan)
    planning = {"closedloop": (300, 5), "openloop": (50, 5)}
    text = est.offline_estimate(cfgs, pending, archs.__getitem__, data_jobs, 2, planning, measures=measures)
    assert seen == [("delta", 512, 1), ("delta", 512, 2), ("gem", 512, 1), ("gem", 512, 2)]
    lines = text.splitlines()
    # data: 1,000 SAC steps x 0.036 s + 2 test episodes x 300 steps x 0.0018 s = 37.08 s = 0.0103 h
    assert lines[2] == "| ant data 0 | 1,000 (0.036 s a step) | 600 (0.0018 s a step) | 0.0103 |"
    # delta: one run (s0 is trained), 10,000 x (0.01 + 0.02) s = 300 s; gem: two runs x 10,000 x 0.06 s = 1,200 s
    assert lines[6] == "| ant-delta | 1 | 20,000 | 512x1 (0.01 s), 512x2 (0.02 s) | 0.0833 |"
    assert lines[7] == "| ant-gem | 2 | 40,000 | 512x1 (0.02 s), 512x2 (0.04 s) | 0.333 |"
    # closed loop: 300 steps x 5 episodes, replanned every step, x 0.2 s = 300 s (a run that may pick either
    # architecture: measured at the larger), gem's second run on its own (200x4) at 0.1 s; open loop: one plan of
    # 50 steps per episode, 5 x 0.5 s
    bound = "(at most: the largest searched architecture)"
    assert lines[11:14] == [f"| ant-delta closedloop cem | 1 | 1,500 | 0.2 {bound} | 0.0833 |",
                            f"| ant-gem closedloop cem | 2 | 3,000 | 0.1-0.2 {bound} | 0.125 |",
                            "| ant-gem openloop cem | 1 | 5 | 0.5 | 0.000694 |"]  # fmt: skip
    # 0.0103 + 0.417 + 0.209 = 0.636 CPU-h; wall 0.0103 + 0.626 / 2 = 0.323 h
    assert lines[15].startswith("1 data set(s) to make, 3 run(s) to train and 2 arm(s) to plan, about 0.636 "
                                "CPU-hours (0.323 h of wall time on 2 worker(s) at best)")  # fmt: skip
    assert "closed-loop episodes that end early cost less" in lines[15]
    nothing = est.offline_estimate(cfgs, {}, archs.__getitem__, [], None, measures=measures)
    assert nothing.startswith("nothing to train, plan or collect")
    epochs = {"ant-delta-s0": make_config("ant", "delta", "research", {"model.iterations": 0})}
    text = est.offline_estimate(epochs, {"ant-delta-s0": train}, archs.__getitem__, [], None, measures=measures)
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
    assert capsys.readouterr().out.startswith("nothing to train, plan or collect")
    plan = ["--closedloop", "--planners", "cem", "--closedloop-steps", "10", "--openloop-episodes", "1",
            "--planner-overrides", "planner.population=20,planner.particles=2"]  # fmt: skip
    assert main([*SWEEP, "--out", str(out), "--estimate", *plan]) == 0  # trained runs: their own architecture
    table = capsys.readouterr().out.splitlines()
    assert table[2].startswith("| invertedpendulum-delta closedloop cem | 2 | 20 | ") and "at most" not in table[2]
    assert main([*SWEEP, "--out", str(out), *plan]) == 0  # the planning, for real
    capsys.readouterr()
    runs = [out / "runs" / f"invertedpendulum-delta-s{s}" for s in (0, 1)]
    executed = [json.loads((r / "closedloop_cem.json").read_text())["lengths"] for r in runs]
    assert sum(map(sum, executed)) <= 20 and all(len(e) == 1 for e in executed)  # episodes that fall end early
    assert main([*SWEEP, "--out", str(out), "--estimate", *plan]) == 0
    assert capsys.readouterr().out.startswith("nothing to train, plan or collect")
    run = out / "runs" / "invertedpendulum-delta-s1"  # a job killed as it wrote the run: a run to train again
    for path in run.iterdir():  # what it wrote after the training's checkpoint, metrics and curves is not there
        if path.is_dir():
            shutil.rmtree(path)
        elif path.name not in ("checkpoint.pt", "metrics.csv", "learning_curve.csv", ".lock"):
            if not path.name.startswith("events.out.tfevents."):
                path.unlink()
    monkeypatch.setattr(est, "_grad_seconds", lambda cfg: 0.001)
    with pytest.raises(SystemExit) as exit_info:  # another config: refused, as the sweep itself refuses it
        main([*replacing(SWEEP, "model.iterations=30"), "--out", str(out), "--estimate"])
    assert exit_info.value.code == 2 and "model.iterations: 20 != 30" in capsys.readouterr().err
    assert main([*SWEEP, "--out", str(out), "--estimate"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| env, arm") and lines[2].startswith("| invertedpendulum-delta | 1 | 60 |")
    assert lines[4].startswith("0 data set(s) to make, 1 run(s) to train and 0 arm(s) to plan")


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
    assert "closed-loop" not in lines[-1]  # none asked for
    monkeypatch.setattr(est, "_plan_seconds", lambda cfg: 0.01)
    assert main([*SWEEP, "--estimate", "--closedloop", "--planners", "cem,mppi", "--closedloop-steps", "40"]) == 0
    lines = capsys.readouterr().out.splitlines()  # 2 runs x 5 episodes x 40 steps, replanned every step
    assert lines[10:12] == ["| invertedpendulum-delta closedloop cem | 2 | 400 | 0.01 (at most: the largest searched "
                            "architecture) | 0.00111 |", "| invertedpendulum-delta closedloop mppi | 2 | 400 | 0.01 "
                            "(at most: the largest searched architecture) | 0.00111 |"]  # fmt: skip
    assert main([*SWEEP, "--policy", "existing", "--estimate"]) == 0  # the user's files: nothing to collect
    assert capsys.readouterr().out.startswith("| env, arm")


def test_a_stopped_sac_collection_counts_what_its_checkpoint_leaves_and_one_it_would_refuse_is_refused(
    tmp_path, monkeypatch, capsys
):
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
    settings = (envs.get("invertedpendulum"), 200, collect_seeds(0)[0], 30)
    assert sac_steps_done(train_path, *settings) == 100 and sac_steps_done(tmp_path / "none.npz", *settings) == 0
    assert main([*SWEEP, "--out", str(out), "--estimate"]) == 0
    assert capsys.readouterr().out.splitlines()[2].startswith("| invertedpendulum data 0 | 100 (0.01 s a step) |")
    # a checkpoint the collection would refuse (written for other settings, or unreadable): the estimate refuses it
    # with the sweep's own line (ground truth: the real sweep, whose data job fails there)
    other_max_steps = [a if a != "30" else "25" for a in SWEEP]
    for sweep, fragment in ((other_max_steps, "(max_steps: 30 != 25)"), (SWEEP, "cannot read the SAC checkpoint")):
        if sweep is SWEEP:
            checkpoint.write_bytes(b"not a checkpoint")
        with pytest.raises(SystemExit) as exit_info:
            main([*sweep, "--out", str(out), "--estimate"])
        assert exit_info.value.code == 2 and fragment in capsys.readouterr().err
        assert main([*sweep, "--out", str(out)]) == EXIT_FAILED
        err = capsys.readouterr().err
        assert "invertedpendulum data 0 failed: UsageError: " in err and fragment in err
    assert checkpoint.read_bytes() == b"not a checkpoint"  # left as it was, for the user to delete
