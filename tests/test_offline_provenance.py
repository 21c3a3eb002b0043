"""prediction.md of ``pets.compare offline`` names what a reviewer needs to redo the comparison, as the online
summary.md does: the seeds, the command that wrote it and the machines its runs were trained and evaluated on (from
each run's eval.json)."""

from __future__ import annotations

import json
import shlex
import socket

from pets.runs.hardware import cpu_name
from tests.test_compare import TINY_OFFLINE, cli


def test_prediction_md_names_the_seeds_the_command_and_the_machines(tmp_path, capsys):
    out = tmp_path / "my off"
    args = ["offline", "--envs", "invertedpendulum", "--models", "delta", "--seeds", "0,1", "--episodes", "3",
            "--test-episodes", "2", "--horizons", "1,3", "--starts", "10", "--out", str(out), "--preset", "fast",
            "--device", "cpu", "--quiet", *TINY_OFFLINE]  # fmt: skip
    code, _, err = cli(capsys, *args)
    assert code == 0, err
    md = (out / "prediction.md").read_text()
    assert f"- command: `python -m pets.compare {shlex.join(args)}`" in md and "'" in md  # the space in OUT quoted
    assert "- seeds: 0, 1 (2); a model's run is paired with delta's run of the same seed" in md
    here = f"{socket.gethostname()} ({cpu_name()})"
    assert f"- machines (runs/RUN/eval.json, where each run was trained and evaluated): {here}: 2 runs" in md
    assert md.index("## How the runs were made") < md.index("## invertedpendulum")
    # a run trained elsewhere and evaluated again here (new horizons) keeps its training's machine: counted on both
    eval_path = out / "runs" / "invertedpendulum-delta-s1" / "eval.json"
    result = json.loads(eval_path.read_text())
    assert result["machines"] == {"train": here, "eval": here}
    eval_path.write_text(json.dumps({**result, "machines": {"train": "otherhost (Other CPU)", "eval": here}}))
    args[args.index("--horizons") + 1] = "1,2"
    code, _, err = cli(capsys, *args)
    assert code == 0 and "0 reused, 2 with work to do" in err, err
    assert json.loads(eval_path.read_text())["machines"] == {"train": "otherhost (Other CPU)", "eval": here}
    md = (out / "prediction.md").read_text()
    assert f"otherhost (Other CPU): 1 run; {here}: 2 runs" in md and "1 runs" not in md
    # runs evaluated before eval.json recorded its machines: said, not guessed
    for run in (out / "runs").iterdir():
        e = json.loads((run / "eval.json").read_text())
        (run / "eval.json").write_text(json.dumps({k: v for k, v in e.items() if k != "machines"}))
    code, _, err = cli(capsys, *args)
    assert code == 0 and "2 reused, 0 with work to do" in err, err
    md = (out / "prediction.md").read_text()
    assert "- machines (runs/RUN/eval.json, where each run was trained and evaluated): not recorded" in md
