"""The config key ``imports`` (pets/imports.py): a planner and a model of your own, registered by a module in your
folder, from the command line (``imports=[MODULE]``), at ``--resume``, in ``pets.PETS.load`` and ``pets.load_model``
of a process that never imported the module, and in ``pets.compare``'s runs; a module that is missing or raises is
one line and exit 2; a run from before the key loads and resumes as it did."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from tests import warm
from tests.test_cli import TINY, cli, error_lines, rows

ROOT = Path(__file__).resolve().parents[1]
#: A module of the user's (tests/own_planner.py, docs/api.md's example): the planner ``random_shooting`` (with its
#: section ``planner.random_shooting.*``) and the model ``delta-mine``, written as my_ext.py into the user's folder.
EXT = (ROOT / "tests" / "own_planner.py").read_text()
#: Opens the run in a process that has not imported the module: PETS.load and pets.load_model import it again.
LOAD = """import sys

assert "my_ext" not in sys.modules
import pets

agent = pets.PETS.load("run")
assert "my_ext" in sys.modules
model = pets.load_model("run")
print(agent.trials_done, agent.config.planner.name, agent.config.head, list(agent.config.imports), type(model).__name__)
"""
#: A codec of the user's (tests/own_codec.py, docs/models.md's example): the kind SO2_wrapped, written as my_codec.py,
#: and an env module of the user's whose layout uses that kind and does not import the codec's module itself.
CODEC = (ROOT / "tests" / "own_codec.py").read_text()
WRAPPED_ENV = """import envs
from envs import Group, ObsLayout

IP = envs.get("invertedpendulum")
LAYOUT = ObsLayout(4, (Group("cart", "Rn", (0,)), Group("hinge", "SO2_wrapped", (1,))), velocities=(2, 3))
SPEC = envs.custom_spec("ip-wrapped", "InvertedPendulum-v5", LAYOUT, IP.reward, IP.terminated)
"""
#: Opens the codec's run in a new process: the head is built on the codec, whose decoding wraps the angle.
LOAD_CODEC = """import math, torch
import pets

agent, model = pets.PETS.load("run"), pets.load_model("run")
nxt = model.head.next_obs(torch.tensor([[0.0, 3.0, 0.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0, 0.0]]))
print(agent.trials_done, [type(c).__name__ for c in model.head.codecs], round(float(nxt[0, 1]), 4))
"""
OWN = [
    "--model",
    "delta-mine",
    "planner.name=random_shooting",
    "planner.random_shooting.spread=0.5",
    "value.enabled=false",
]


def run_here(args: list, cwd: Path, script: Path = ROOT / "run_pets.py"):
    """``python SCRIPT ARGS`` as a user runs it in ``cwd`` (the module is importable only from there)."""
    cmd = [sys.executable, str(script), *map(str, args)]
    return warm.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=300)


def one_line(proc) -> str:
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    return lines[0]


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    me = tmp_path / "me"
    me.mkdir()
    (me / "my_ext.py").write_text(EXT)
    return me


def test_own_planner_and_model_from_the_command_line_resume_and_load(folder: Path, tmp_path: Path) -> None:
    """imports=[my_ext] runs a trial with the module's planner and model; --resume and PETS.load / load_model in a
    process that never imported it import it again from config.yaml; from another folder, one line says where."""
    args = ["--env", "invertedpendulum", "--trials", 1, "--out", "run", *TINY, *OWN, "imports=[my_ext]"]
    proc = run_here(args, folder)
    assert proc.returncode == 0, proc.stderr
    written = OmegaConf.load(folder / "run" / "config.yaml")
    assert (
        list(written.imports) == ["my_ext"]
        and written.planner.name == "random_shooting"
        and written.head == "delta-mine"
    )
    assert written.planner.random_shooting.spread == 0.5
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    line = one_line(run_here(["--resume", folder / "run", "--trials", 2], elsewhere))
    assert "config.yaml: imports: cannot import 'my_ext'" in line and "the folder that holds my_ext.py" in line
    assert run_here(["--resume", "run", "--trials", 2, "--quiet"], folder).returncode == 0
    assert [int(r["trial"]) for r in rows(folder / "run")] == [0, 1]
    (elsewhere / "load.py").write_text(LOAD)  # the script's own folder is not the module's
    proc = run_here([], folder, script=elsewhere / "load.py")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["2", "random_shooting", "delta-mine", "['my_ext']", "DynamicsModel"]


def test_one_name_without_brackets_and_a_config_file_take_the_same_list(folder: Path) -> None:
    """imports=my_ext (one name) and imports: [my_ext] in a --config file are imports=[my_ext]; --print-config
    writes the list, a valid --config file."""
    single = run_here(["--env", "invertedpendulum", "--print-config", *OWN, "imports=my_ext"], folder)
    assert single.returncode == 0, single.stderr
    (folder / "mine.yaml").write_text("imports: [my_ext]\nplanner:\n  name: random_shooting\n")
    args = ["--env", "invertedpendulum", "--print-config", "--model", "delta-mine", "--config", "mine.yaml"]
    from_file = run_here([*args, "planner.random_shooting.spread=0.5", "value.enabled=false"], folder)
    assert from_file.returncode == 0, from_file.stderr
    assert single.stdout == from_file.stdout and single.stdout.startswith("imports:\n- my_ext\n")


@pytest.mark.parametrize(
    "module, value, fragment",
    [
        (None, "imports=[nope]", "imports: cannot import 'nope' (No module named 'nope'); run the command from the "
         "folder that holds nope.py (or put that folder on PYTHONPATH), or drop it from imports"),
        ("raise RuntimeError('no GPU here')\n", "imports=[bad]",
         "imports: importing 'bad' failed (RuntimeError: no GPU here); fix the module, or drop it from imports"),
        ("def (:\n", "imports=bad", "imports: importing 'bad' failed (SyntaxError"),
        ("import not_installed_dep\n", "imports=[bad]",
         "importing 'bad' failed (ModuleNotFoundError: No module named 'not_installed_dep'); install what it imports"),
        ("import sys\nsys.exit(0)\n", "imports=[bad]", "imports: importing 'bad' exited (SystemExit: 0)"),
        (None, "imports=[1]", "imports must be a list of non-empty module names"),
        (None, "imports=[my_ext, '']", "imports must be a list of non-empty module names"),
        (None, "imports={a: 1}", "imports: '{a: 1}' is not a module name"),
        (None, "imports=[my_ext.py]", "imports: 'my_ext.py' is a file name; give the module name (my_ext)"),
        (None, "imports=[a b]", "imports: 'a b' is not a module name"),
        (None, "imports=[a", "imports: '[a' is not a list"),
    ],
)  # fmt: skip
def test_a_bad_imports_value_or_module_is_one_line_and_exit_2(folder, module, value, fragment) -> None:
    if module is not None:
        (folder / "bad.py").write_text(module)
    line = one_line(run_here(["--env", "invertedpendulum", "--trials", 1, "--out", "run", *TINY, value], folder))
    assert fragment in line and not (folder / "run").exists()


def test_an_unknown_planner_or_model_says_imports(folder: Path) -> None:
    """Without the module, the planner and the model are unknown: the line says what to add."""
    line = one_line(run_here(["--env", "invertedpendulum", "--print-config", "planner.name=random_shooting"], folder))
    assert "got 'random_shooting' (a planner of your own is known where the module that calls register_" in line
    assert "imports=[my_planner]" in line
    line = one_line(run_here(["--env", "invertedpendulum", "--print-config", "--model", "delta-mine"], folder))
    assert line.startswith("run_pets.py: error: --model delta-mine: accepted models: delta, gem")
    assert "the module that calls register_model is imported" in line and "imports=[my_model]" in line


@pytest.fixture
def registrations(monkeypatch, folder: Path):
    """In this process, from ``folder`` (the planner and the model the module registers are gone after the test:
    tests/conftest.py)."""
    monkeypatch.chdir(folder)
    monkeypatch.setattr(sys, "path", list(sys.path))


def test_make_config_and_load_config_import_first_in_this_process(registrations, tmp_path: Path) -> None:
    """The API's make_config imports before planner.<name>.* keys and the model are checked; load_config of a
    config.yaml imports before its planner is; a module that fails there names the file."""
    from pets.config import ConfigError, all_keys, config_yaml, load_config, make_config

    assert "planner.random_shooting.spread" not in all_keys()
    overrides = {"imports": ["my_ext"], "planner.name": "random_shooting", "planner.random_shooting.spread": "0.25"}
    cfg = make_config("invertedpendulum", "delta-mine", "fast", overrides)
    assert cfg.planner.random_shooting.spread == 0.25 and list(cfg.imports) == ["my_ext"] and "my_ext" in sys.modules
    (tmp_path / "config.yaml").write_text(config_yaml(cfg))
    assert load_config(tmp_path / "config.yaml") == cfg
    (tmp_path / "config.yaml").write_text(config_yaml(cfg).replace("- my_ext", "- my_ext_gone"))
    with pytest.raises(ConfigError, match=r"config\.yaml: imports: cannot import 'my_ext_gone'") as err:
        load_config(tmp_path / "config.yaml")
    assert "\n" not in str(err.value)
    assert list(make_config("invertedpendulum").imports) == []


def test_a_run_from_before_the_key_loads_and_resumes_as_it_did(tmp_path: Path) -> None:
    """A run whose config.yaml and checkpoint have no imports (written before the key existed) resumes; its
    config.yaml may then be given the key (the modules that register its planner or model) without being called
    edited, while a run that recorded its imports may not drop one."""
    from pets.config import ConfigError, load_run_config
    from pets.runs import rundir

    out = tmp_path / "run"
    cli("--env", "invertedpendulum", "--trials", 1, "--out", out, *TINY)
    written = OmegaConf.load(out / "config.yaml")
    del written["imports"]
    OmegaConf.save(written, out / "config.yaml")
    state = rundir.load_checkpoint(out)
    del state["config"]["imports"]
    rundir.save_checkpoint(out, state)
    assert "imports" not in (out / "config.yaml").read_text()
    assert list(load_run_config(out).imports) == []
    cli("--resume", out, "--trials", 2)
    assert [int(r["trial"]) for r in rows(out)] == [0, 1]
    old = rundir.load_checkpoint(out)
    assert old["config"]["imports"] == []  # the resumed run's checkpoint has the key, at its default
    del old["config"]["imports"]
    (out / "config.yaml").write_text("imports: [json]\n" + (out / "config.yaml").read_text())
    rundir.check_resumed_config(out, old, load_run_config(out))  # not an edit: the checkpoint predates the key
    recorded = {**old, "config": {**old["config"], "imports": ["os"]}}  # a module recorded, then dropped
    with pytest.raises(ConfigError, match=r"was edited after the run started \(imports: \['os'\] in the checkpoint"):
        rundir.check_resumed_config(out, recorded, load_run_config(out))


def test_pets_compare_passes_imports_to_its_runs(folder: Path) -> None:
    """pets.compare online with a model of one's own: --models takes it after the imports, and every run gets
    imports=[my_ext] (its config.yaml records it)."""
    cmd = [sys.executable, "-m", "pets.compare", "online", "--envs", "invertedpendulum", "--models", "delta-mine",
           "--arm", "mine-h3=delta-mine:planner.horizon=3", "--seeds", "0", "--trials", "1", "--out", "cmp", *TINY,
           "planner.name=random_shooting", "value.enabled=false", "imports=[my_ext]"]  # fmt: skip
    proc = warm.run(cmd, cwd=folder, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    runs = sorted((folder / "cmp" / "runs").iterdir())
    assert [r.name for r in runs] == ["invertedpendulum-delta-mine-s0", "invertedpendulum-mine-h3-s0"]
    for run in runs:  # the arm of one's own model too (--arm is read after the imports)
        written = OmegaConf.load(run / "config.yaml")
        assert (
            list(written.imports) == ["my_ext"]
            and written.head == "delta-mine"
            and written.planner.name == "random_shooting"
        )
    assert OmegaConf.load(runs[1] / "config.yaml").planner.horizon == 3


def test_pets_compare_offline_trains_a_model_of_ones_own_in_its_worker_processes(folder: Path) -> None:
    """pets.compare offline with a model of one's own and --workers 2: the spawned workers import the module from
    the runs' config (delta-mine is delta bit for bit: the ratio is 1)."""
    cmd = [sys.executable, "-m", "pets.compare", "offline", "--envs", "invertedpendulum", "--models",
           "delta,delta-mine", "--seeds", "0", "--episodes", "3", "--test-episodes", "1", "--horizons", "1,2",
           "--starts", "10", "--preset", "fast", "--device", "cpu", "--quiet", "--workers", "2", "--out", "off",
           "imports=[my_ext]", "model.max_epochs=2", "model.hidden_size=32", "model.ensemble_size=2",
           "model.num_elites=2", "model.batch_size=32"]  # fmt: skip
    proc = warm.run(cmd, cwd=folder, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    written = OmegaConf.load(folder / "off" / "runs" / "invertedpendulum-delta-mine-s0" / "config.yaml")
    assert list(written.imports) == ["my_ext"] and written.head == "delta-mine"
    assert "| invertedpendulum | 1 2 | delta-mine | 1 | 0 |" in proc.stdout


def test_pets_train_and_pets_evaluate_with_a_model_of_ones_own(folder: Path) -> None:
    """pets.train takes --model of one's own after imports=[my_ext] and records it; pets.evaluate of that run, in a
    new process, imports the module again from the run's config.yaml."""

    def run(*args: str) -> subprocess.CompletedProcess:
        return warm.run([sys.executable, "-m", *args], cwd=folder, capture_output=True, text=True, timeout=300)

    proc = run("pets.collect", "--env", "invertedpendulum", "--policy", "random", "--episodes", "3", "--max-steps",
               "30", "--out", "d.npz", "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    proc = run("pets.train", "--data", "d.npz", "--model", "delta-mine", "--out", "t", "--epochs", "2", "--quiet",
               "imports=[my_ext]", "model.hidden_size=32", "model.ensemble_size=2", "model.num_elites=2")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    written = OmegaConf.load(folder / "t" / "config.yaml")
    assert list(written.imports) == ["my_ext"] and written.head == "delta-mine"
    proc = run("pets.evaluate", "--run", "t", "--data", "d.npz", "--horizons", "1,2", "--starts", "5")
    assert proc.returncode == 0 and "delta-mine" in proc.stdout, proc.stdout + proc.stderr


def test_no_modules_is_an_empty_list_however_it_is_written() -> None:
    from pets.imports import module_names

    for empty in ("", "null", "[]", None, []):
        assert module_names(empty) == []
    assert module_names("json") == ["json"] and module_names("[json, os.path]") == ["json", "os.path"]


def test_a_model_registered_by_a_module_the_api_process_imported_itself_reopens_once_config_yaml_names_it(
    registrations, folder: Path, monkeypatch
) -> None:
    """pets.PETS with a model whose module the script imported itself (not through imports) records imports: [];
    a new process cannot know the model (one line naming imports), and once config.yaml names the module (adding
    modules to imports is not an edit; dropping one is: test_a_run_from_before_the_key_loads_and_resumes_as_it_did)
    --resume and PETS.load / load_model reopen the run."""
    import pets

    monkeypatch.syspath_prepend(str(folder))
    import my_ext  # noqa: F401  (the script's own import: registers delta-mine in this process only)

    tiny = {k: v for k, _, v in (item.partition("=") for item in TINY if "=" in item)}
    agent = pets.PETS("invertedpendulum", model="delta-mine", preset="fast", seed=0, **tiny, **{"value.enabled": False})
    agent.learn(trials=1)
    agent.save("run")
    written = OmegaConf.load(folder / "run" / "config.yaml")
    assert list(written.imports) == [] and written.head == "delta-mine"
    line = one_line(run_here(["--resume", "run", "--trials", 2, "--quiet"], folder))
    assert "its planner 'random_shooting' is not a planner here" in line and "imports: [my_planner]" in line
    written.imports = ["my_ext"]
    OmegaConf.save(written, folder / "run" / "config.yaml")
    assert run_here(["--resume", "run", "--trials", 2, "--quiet"], folder).returncode == 0
    assert [int(r["trial"]) for r in rows(folder / "run")] == [0, 1]
    (folder / "load.py").write_text(LOAD)
    proc = run_here([], folder, script=folder / "load.py")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["2", "mppi", "delta-mine", "['my_ext']", "DynamicsModel"]


def test_a_codec_of_ones_own_from_imports_runs_resumes_loads_collects_and_evaluates(folder: Path) -> None:
    """--env my_env:SPEC, whose layout uses the kind SO2_wrapped, with imports=[my_codec] (the module that registers
    the codec) runs a gem trial on the codec; without imports, one line that says imports=[my_codec]; --resume,
    PETS.load / load_model, pets.collect --policy run: and pets.evaluate in new processes import it again."""
    (folder / "my_codec.py").write_text(CODEC)
    (folder / "my_env.py").write_text(WRAPPED_ENV)
    args = ["--env", "my_env:SPEC", "--model", "gem", "--trials", 1, "--out", "run", *TINY, "value.enabled=false"]
    line = one_line(run_here(args, folder))
    assert "unknown kind 'SO2_wrapped'" in line and "imports=[my_codec]" in line and not (folder / "run").exists()
    proc = run_here([*args, "imports=[my_codec]"], folder)
    assert proc.returncode == 0, proc.stderr
    written = OmegaConf.load(folder / "run" / "config.yaml")
    assert list(written.imports) == ["my_codec"] and written.env == "my_env:SPEC" and written.head == "gem"
    assert run_here(["--resume", "run", "--trials", 2, "--quiet"], folder).returncode == 0
    assert [int(r["trial"]) for r in rows(folder / "run")] == [0, 1]
    (folder / "load.py").write_text(LOAD_CODEC)
    proc = run_here([], folder, script=folder / "load.py")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["2", "['RnCodec',", "'SO2WrappedCodec']", str(round(4.0 - 2 * math.pi, 4))]

    def tool(*cmd: str) -> subprocess.CompletedProcess:
        return warm.run([sys.executable, "-m", *cmd], cwd=folder, capture_output=True, text=True, timeout=300)

    proc = tool("pets.collect", "--policy", "run:run", "--episodes", "2", "--max-steps", "20", "--out", "d.npz")
    assert proc.returncode == 0, proc.stderr
    proc = tool("pets.evaluate", "--run", "run", "--data", "d.npz", "--horizons", "1,2", "--starts", "4", "--json", "e")
    assert proc.returncode == 0, proc.stderr
    result = json.loads((folder / "e").read_text())
    assert result["env"] == "my_env:SPEC" and math.isfinite(result["horizons"]["2"]["rotation_error"])
    assert result["horizons"]["2"]["rotation_error"] > 0


def test_a_codec_of_ones_own_from_imports_in_the_python_api(registrations, folder: Path) -> None:
    """pets.PETS(..., imports=["my_codec"]) imports the codec's module before the env's layout is built: the model's
    head runs on the codec, and the config records the module."""
    import pets

    (folder / "my_codec.py").write_text(CODEC)
    (folder / "my_env.py").write_text(WRAPPED_ENV)
    agent = pets.PETS("my_env:SPEC", model="gem", preset="fast", imports=["my_codec"], **{"model.compile": False})
    assert [c.kind for c in agent.model.head.codecs] == ["Rn", "SO2_wrapped"]
    assert list(agent.config.imports) == ["my_codec"] and agent.config.env == "my_env:SPEC"


def test_pets_collect_env_takes_imports_for_a_codec_its_module_does_not_import(tmp_path: Path) -> None:
    """pets.collect --env tests.custom_envs:wrapped_pendulum (a layout of the kind SO2_wrapped; its module does not
    import tests.own_codec) collects with imports=[tests.own_codec], before or after the options; without it, one
    line that says imports=[my_codec]; another config key is one line naming it; nothing is written on refusal."""
    out = tmp_path / "d.npz"

    def collect(*extra: str) -> subprocess.CompletedProcess:
        cmd = [sys.executable, "-m", "pets.collect", "--env", "tests.custom_envs:wrapped_pendulum", "--policy",
               "random", "--episodes", "2", "--max-steps", "10", "--quiet", *extra]  # fmt: skip
        return warm.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)

    line = one_line(collect("--out", str(out)))
    assert "unknown kind 'SO2_wrapped'" in line and "imports=[my_codec]" in line and not out.exists()
    line = one_line(collect("--out", str(out), "imports=[tests.own_codec]", "seed=1"))
    assert "takes one config key, imports=[MODULE,...], got seed=1" in line and "--seed" in line and not out.exists()
    proc = collect("imports=[tests.own_codec]", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    from pets.data.datasets import load_dataset

    data = load_dataset(out)
    assert str(data["env"]) == "tests.custom_envs:wrapped_pendulum" and len(data["lengths"]) == 2
