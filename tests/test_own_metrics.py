"""An error metric of one's own (pets.learning.error_metrics.register_metric), end to end: a user's module named in
the config key imports registers a max-abs-error metric; pets.compare offline trains tiny models with it, evaluates
them and summarises it as it does the built-in errors; pets.evaluate (the command, in the user's folder) imports it
again from the run's config.yaml and shows it. Ground truth: numpy on the model's own rollout from the eval.json's
start points, and the evaluation without the metric (the built-in numbers do not move)."""

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pets import builder
from pets.config import ConfigError, make_config
from pets.data.datasets import load_dataset
from pets.experiments.offline import compare_offline
from pets.learning import error_metrics
from pets.learning.evaluation import HORIZON_KEYS, METRICS, evaluate, register_metric

ROOT = Path(__file__).resolve().parents[1]
TINY_OFFLINE = [  # tests/test_compare.py's tiny offline settings
    "model.max_epochs=3",
    "model.hidden_size=32",
    "model.ensemble_size=2",
    "model.num_elites=2",
    "model.batch_size=32",
]
HORIZONS = ("1", "3", "5")
MY_METRIC = """\
from pets.learning.evaluation import register_metric


def max_abs_error(pred, true, layout):
    return (pred - true).abs().amax(dim=-1)


register_metric("max_abs_error", max_abs_error)
"""


def _tiny_study(out: Path) -> dict:
    """pets.compare offline of delta, seeds 0 and 1, on a tiny InvertedPendulum data set, importing my_metric."""
    return compare_offline(
        ["invertedpendulum"],
        ["delta"],
        [0, 1],
        out,
        episodes=8,
        test_episodes=4,
        horizons=[int(h) for h in HORIZONS],
        starts=20,
        preset="fast",
        device="cpu",
        overrides=[*TINY_OFFLINE, "imports=[my_metric]"],
        progress=False,
    )


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """pets.compare offline of delta, seeds 0 and 1, with imports=[my_metric] (my_metric.py in the user's folder,
    the current one); the metric and the module are forgotten after the module's tests."""
    folder = tmp_path_factory.mktemp("user")
    (folder / "my_metric.py").write_text(MY_METRIC)
    before, modules = dict(error_metrics.METRIC_TABLE), set(sys.modules)
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(folder)
        mp.syspath_prepend(str(folder))
        result = _tiny_study(folder / "out")
        yield folder, folder / "out", result
    error_metrics.METRIC_TABLE.clear()
    error_metrics.METRIC_TABLE.update(before)
    for name in set(sys.modules) - modules:
        if name == "my_metric":
            sys.modules.pop(name)


def csv_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def eval_json(out, seed):
    return json.loads((out / "runs" / f"invertedpendulum-delta-s{seed}" / "eval.json").read_text())


def test_the_metric_is_in_eval_json_and_equals_numpy_on_the_same_rollout(study):
    """eval.json holds max_abs_error after the built-in metrics, before nonfinite_fraction, per horizon the mean over
    the starts and k = 1..h of max_i |pred_i - true_i|, recomputed here in numpy from the model's mean rollout."""
    folder, out, result = study
    assert result["failed"] == {}
    run_dir = out / "runs" / "invertedpendulum-delta-s0"
    assert "my_metric" in (run_dir / "config.yaml").read_text()  # recorded: loading the run imports it again
    res = eval_json(out, 0)
    assert list(res["horizons"]) == list(HORIZONS)
    assert all(tuple(row) == (*METRICS, "max_abs_error", "nonfinite_fraction") for row in res["horizons"].values())
    data = load_dataset(out / "data" / "invertedpendulum-test.npz")
    pairs = np.array(res["start_points"])
    ep, t0 = pairs[:, 0], pairs[:, 1]
    steps = t0[:, None] + np.arange(int(HORIZONS[-1]) + 1)[None, :]
    obs, act = (
        np.asarray(data["obs"], np.float64)[ep[:, None], steps],
        np.asarray(data["act"])[ep[:, None], steps[:, :-1]],
    )
    _, _, model = builder.load_model(run_dir, torch.device("cpu"))
    with torch.no_grad():
        pred = model.rollout(
            torch.as_tensor(obs[:, 0]).float(), torch.as_tensor(act, dtype=torch.float32), "mean", torch.Generator()
        )
    err = np.abs(pred.double().numpy() - obs[:, 1:]).max(axis=-1)  # (starts, H)
    for h, row in res["horizons"].items():
        want = err[:, : int(h)].mean()
        assert row["max_abs_error"] == pytest.approx(want, rel=1e-6) and want > 0
        assert row["max_abs_error"] >= row["mean_step_error"] / np.sqrt(obs.shape[-1]) - 1e-12  # max >= rms


def test_registering_a_metric_leaves_the_built_in_numbers_as_they_were(study, monkeypatch):
    folder, out, _ = study
    monkeypatch.chdir(folder)
    run_dir, data = out / "runs" / "invertedpendulum-delta-s1", out / "data" / "invertedpendulum-test.npz"
    with_metric = evaluate(run_dir, data, [1, 5], starts=15, seed=2, device="cpu")
    monkeypatch.delitem(error_metrics.METRIC_TABLE, "max_abs_error")  # my_metric stays imported: not registered again
    without = evaluate(run_dir, data, [1, 5], starts=15, seed=2, device="cpu")
    for h in ("1", "5"):
        assert tuple(without["horizons"][h]) == HORIZON_KEYS
        assert {k: with_metric["horizons"][h][k] for k in HORIZON_KEYS} == without["horizons"][h]


def test_the_offline_summary_has_the_metric_as_the_built_in_ones(study):
    """summary.csv and relative_error.csv get rows of max_abs_error, prediction_runs.csv a column; two seeds: the
    IQM is their mean and the CI [min, max]."""
    _, out, _ = study
    evals = {seed: eval_json(out, seed) for seed in (0, 1)}
    rows = {r["horizon"]: r for r in csv_rows(out / "summary.csv") if r["metric"] == "max_abs_error"}
    assert set(rows) == set(HORIZONS)
    for h, r in rows.items():
        values = [evals[s]["horizons"][h]["max_abs_error"] for s in (0, 1)]
        assert (r["model"], int(r["n_seeds"]), int(r["n_diverged"])) == ("delta", 2, 0)
        assert float(r["iqm"]) == pytest.approx(np.mean(values), rel=1e-12)
        assert (float(r["ci_low"]), float(r["ci_high"])) == (min(values), max(values))
    runs = csv_rows(out / "prediction_runs.csv")
    assert list(runs[0])[list(runs[0]).index("standardized_error") + 1] == "max_abs_error"
    for r in runs:
        assert float(r["max_abs_error"]) == evals[int(r["seed"])]["horizons"][r["horizon"]]["max_abs_error"]
    assert [r["metric"] for r in csv_rows(out / "relative_error.csv")].count("max_abs_error") == 1


def test_pets_evaluate_imports_the_metric_from_the_runs_config_and_shows_it(study, tmp_path):
    """The command, run in the user's folder, imports my_metric from the run's config.yaml (imports: [my_metric]):
    a column of its table and a key of its JSON, equal to the offline study's evaluation with the same request."""
    folder, out, _ = study
    run_dir = out / "runs" / "invertedpendulum-delta-s0"
    args = ["--run", run_dir, "--data", out / "data" / "invertedpendulum-test.npz", "--horizons", "1,3,5"]
    args += ["--starts", 20, "--device", "cpu", "--threads", 1, "--json", tmp_path / "eval.json"]
    args += ["--train-data", out / "data" / "invertedpendulum-train.npz"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [sys.executable, "-m", "pets.evaluate", *map(str, args)], cwd=folder, env=env, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    head = proc.stdout.splitlines()[1].split()
    assert head == ["horizon", *METRICS, "max_abs_error"]
    res, study_res = json.loads((tmp_path / "eval.json").read_text()), eval_json(out, 0)
    assert res["start_points"] == study_res["start_points"]
    for h in HORIZONS:
        assert res["horizons"][h]["max_abs_error"] == pytest.approx(study_res["horizons"][h]["max_abs_error"], rel=1e-6)
    # elsewhere, where my_metric.py cannot be imported: one line, saying what to do
    proc = subprocess.run(
        [sys.executable, "-m", "pets.evaluate", *map(str, args)], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert "cannot import 'my_metric'" in proc.stderr


def test_a_name_that_clashes_or_is_not_an_error_key_is_refused_in_one_line(tmp_path, monkeypatch):
    def mine(pred, true, layout):
        return (pred - true).abs().sum(-1)

    for name in ("rotation_error", "nonfinite_fraction"):
        with pytest.raises(ValueError, match=f"metric name '{name}' is a built-in metric of pets.evaluate"):
            register_metric(name, mine)
    for name in ("max_abs", "Max_error", "max abs_error", 3):
        with pytest.raises(ValueError, match="must be lower-case letters, digits and underscores ending in _error"):
            register_metric(name, mine)
    with pytest.raises(ValueError, match="metric 'mine_error' must be a callable"):
        register_metric("mine_error", "mine")
    assert register_metric("mine_error", mine) is mine
    register_metric("mine_error", mine)  # the same again (its module imported again): accepted

    def other(pred, true, layout):
        return (pred - true).abs().amax(-1)

    with pytest.raises(
        ValueError, match=r"metric name 'mine_error' is taken \(registered by \S*test_own_metrics\S*\.mine\)"
    ):
        register_metric("mine_error", other)
    # from a module of imports: the config refuses it in one line
    (tmp_path / "clash_metric.py").write_text(
        "from pets.learning.evaluation import register_metric\n"
        "register_metric('standardized_error', lambda pred, true, layout: (pred - true).abs().sum(-1))\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    with pytest.raises(ConfigError) as info:
        make_config("invertedpendulum", preset="fast", overrides={"imports": ["clash_metric"]})
    assert "metric name 'standardized_error' is a built-in metric" in str(info.value)
    assert "\n" not in str(info.value)


def test_a_metric_of_the_wrong_shape_is_named(study, monkeypatch):
    folder, out, _ = study
    monkeypatch.chdir(folder)

    class Total:  # a class instance is a metric too; this one sums over the steps as well: one value per start
        def __call__(self, pred, true, layout):
            return (pred - true).abs().sum(dim=(-2, -1))

    register_metric("total_abs_error", Total())
    run_dir, data = out / "runs" / "invertedpendulum-delta-s0", out / "data" / "invertedpendulum-test.npz"
    with pytest.raises(
        ValueError, match=r"metric 'total_abs_error' \(.*Total\) must return a tensor of shape \(\d+, 3\)"
    ):
        evaluate(run_dir, data, [1, 3], starts=10, device="cpu")


def test_a_metric_added_to_the_module_later_re_evaluates_the_runs_without_retraining(study, tmp_path, monkeypatch):
    """The same imports, the module now registering a second metric: pets.compare offline in the same --out redoes
    the evaluations (their request names the metrics), not the training, and summarises both."""
    folder, out, _ = study
    shutil.copytree(out, tmp_path / "out")
    (tmp_path / "my_metric.py").write_text(
        MY_METRIC + "register_metric('sum_abs_error', lambda pred, true, layout: (pred - true).abs().sum(-1))\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "my_metric")  # a new process would import the edited module
    before = eval_json(tmp_path / "out", 0)
    result = _tiny_study(tmp_path / "out")
    assert result["failed"] == {} and all(done == ["eval"] for done in result["done"].values()), result["done"]
    after = eval_json(tmp_path / "out", 0)
    assert after["request"]["metrics"] == ["max_abs_error", "sum_abs_error"] and before["request"]["metrics"] == [
        "max_abs_error"
    ]
    for h in HORIZONS:
        assert tuple(after["horizons"][h])[-3:] == ("max_abs_error", "sum_abs_error", "nonfinite_fraction")
        assert after["horizons"][h]["max_abs_error"] == pytest.approx(before["horizons"][h]["max_abs_error"], rel=1e-6)
    metrics = {r["metric"] for r in csv_rows(tmp_path / "out" / "summary.csv")}
    assert {"max_abs_error", "sum_abs_error", "mean_step_error"} <= metrics
