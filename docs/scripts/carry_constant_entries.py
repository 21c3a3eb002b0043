"""Re-evaluate trained offline runs with some observation entries carried over unchanged instead of predicted
(docs/results.md, "Reacher, whole state"): how much of a gap between heads those entries explain.

    python docs/scripts/carry_constant_entries.py STUDY_DIR ENV MODELS SEEDS ENTRIES [HORIZON]

e.g. ``python docs/scripts/carry_constant_entries.py results/paper-reacher reacher delta,gem 0,1,2,3,4,5,6,7,8,9
4,5``: per run the standardized, translation and rotation errors at HORIZON (50) as evaluated (the study's
request: 1000 start points, seed 0, mean mode, standardised by the training data), then with the ENTRIES
copied from the current observation at every predicted step (exact for entries that never change within an
episode, like Reacher's target position); per model the median over seeds and the paired median ratio to the
first model. The trained models are not changed.
"""

import sys

import numpy as np
import torch

from pets.learning.evaluation import evaluate_loaded, load_inputs

torch.set_num_threads(1)
study, env = sys.argv[1], sys.argv[2]
models, seeds = sys.argv[3].split(","), [int(s) for s in sys.argv[4].split(",")]
entries = [int(i) for i in sys.argv[5].split(",")]
horizon = int(sys.argv[6]) if len(sys.argv) > 6 else 50
keys = ("standardized_error", "translation_error", "rotation_error", "mean_step_error")
table = {}
for model in models:
    for seed in seeds:
        inputs = load_inputs(
            f"{study}/runs/{env}-{model}-s{seed}",
            f"{study}/data/{env}-test.npz",
            [horizon],
            1000,
            "mean",
            "cpu",
            f"{study}/data/{env}-train.npz",
        )
        m = inputs["model"]
        as_is = evaluate_loaded(inputs)["horizons"][str(horizon)]
        predict = m.next_obs

        def carried(obs, target, predict=predict):
            out = predict(obs, target).clone()
            out[..., entries] = obs[..., entries].to(out.dtype)
            return out

        m.next_obs = carried
        carried_result = evaluate_loaded(inputs)["horizons"][str(horizon)]
        table[model, seed] = {"as is": as_is, "carried": carried_result}
print(f"{env}, h={horizon}, entries {entries} carried; median over seeds {seeds} [paired median ratio to {models[0]}]")
for variant in ("as is", "carried"):
    for key in keys:
        cells = []
        for model in models:
            vals = np.array([table[model, s][variant][key] for s in seeds])
            base = np.array([table[models[0], s][variant][key] for s in seeds])
            ratio = np.median(vals / base) if model != models[0] and base.all() else np.nan
            cells.append(f"{model} {np.median(vals):.4g}" + ("" if np.isnan(ratio) else f" [{ratio:.2f}]"))
        print(f"{variant:>8} {key:>19}: " + ", ".join(cells))
