"""One-step error per observation entry of trained offline runs (docs/results.md, "Reacher: where GEM loses").

    python docs/scripts/onestep_per_dim.py STUDY_DIR ENV MODELS SEEDS [N]

e.g. ``python docs/scripts/onestep_per_dim.py results/paper-reacher reacher delta,gem,delta-groupfeat 0,1,2,3,4``:
per model the RMSE of the ensemble-mean one-step prediction for every observation entry on the first N (5000)
transitions of STUDY_DIR/data/ENV-test.npz, the median over the seeds, and each target slot's std in the test
transitions (0: the entry never changes).
"""

import sys

import numpy as np
import torch

from pets import builder

torch.set_num_threads(1)
study, env, models, seeds = sys.argv[1], sys.argv[2], sys.argv[3].split(","), [int(s) for s in sys.argv[4].split(",")]
n = int(sys.argv[5]) if len(sys.argv) > 5 else 5000
data = np.load(f"{study}/data/{env}-test.npz")
obs_dim = data["obs"].shape[-1]
# transitions inside each episode (obs t -> t + 1 for t < length)
pairs = [(e, t) for e, length in enumerate(data["lengths"]) for t in range(int(length))][:n]
e, t = (np.array(x) for x in zip(*pairs))
obs = torch.tensor(data["obs"][e, t], dtype=torch.float32)
nxt = torch.tensor(data["obs"][e, t + 1], dtype=torch.float32)
act = torch.tensor(data["act"][e, t], dtype=torch.float32)
np.set_printoptions(precision=5, suppress=True, linewidth=160)
print(f"{env}: {len(pairs)} test transitions; RMSE per observation entry (median over seeds {seeds})")
for model in models:
    rmse = []
    for seed in seeds:
        _, _, m = builder.load_model(f"{study}/runs/{env}-{model}-s{seed}", torch.device("cpu"))
        with torch.no_grad():
            mean, _ = m(m.inputs(obs, act))
            pred = m.next_obs(obs, mean.mean(0))
        rmse.append(((pred - nxt) ** 2).mean(0).sqrt().numpy())
    print(f"{model:>16}: {np.median(np.array(rmse), 0)}")
print(f"{'entry std':>16}: {(nxt - obs).std(0).numpy()} (of next - current)")
