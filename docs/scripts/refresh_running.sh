#!/usr/bin/env bash
# The committed rows of the running studies, refreshed from the run directories under ROOT (default /work/runs):
# ROOT/gate/* (gate runs; *.npz SAC data sets with *.cpu_s), ROOT/pilots/*, ROOT/online/*, ROOT/composition. Rows of runs whose
# directories are not here (finished on a machine since replaced) are kept as committed (--replace not given);
# then the report regenerates every generated table and figure, and --check confirms it.
#     bash docs/scripts/refresh_running.sh [ROOT]
set -euo pipefail
root=${1:-/work/runs}
cd "$(dirname "$0")/../.."
shopt -s nullglob
gate=("$root"/gate/*/config.yaml) sac=("$root"/gate/*.npz) pilots=("$root"/pilots/*/config.yaml)
peer=(docs/results/peer_gate_*.csv)  # mbrl-lib's runs (peer_mbrl.py learn --out), committed as they finish
online=("$root"/online/*/config.yaml)
if ((${#gate[@]} + ${#sac[@]} + ${#peer[@]})); then
  python -m pets.experiments.gate "${gate[@]%/config.yaml}" --sac "${sac[@]}" --peer "${peer[@]}" \
    --out docs/results/locomotion_gate >/dev/null
fi
if ((${#pilots[@]})); then
  python -m pets.experiments.gate "${pilots[@]%/config.yaml}" --pilots --out docs/results/locomotion_pilots >/dev/null
fi
if ((${#online[@]})); then
  python -m pets.experiments.studies.locomotion "${online[@]%/config.yaml}" --identical \
    --out docs/results/online_locomotion_runs.csv --curves docs/results/online_locomotion_curves.csv >/dev/null
fi
# The composition study's snapshot: every finished run of ROOT/composition/results (a remade data set's runs
# replace the withdrawn ones: docs/studies/composition.md, amendment of 2026-11-28 21:30 UTC).
if compgen -G "$root/composition/results/runs/*/eval.json" >/dev/null; then
  summary=$(mktemp -d) names=$(ls "$root/composition/results/runs")
  envs=$(cut -d- -f1 <<<"$names" | sort -u | paste -sd,)  # run names: ENV-MODEL[-dDATA]-sSEED (data set 0: no -d)
  data=$( (echo 0; grep -o -- '-d[0-9]*-s' <<<"$names" || true) | tr -dc '0-9\n' | sort -un | paste -sd,)
  python docs/scripts/partial_offline_runs.py "$root/composition/results" docs/results/composition_runs_partial.csv \
    --summary "$summary" --envs "$envs" --models delta-groupfeat,gem,gem-se,delta --seeds 0,1,2,3,4 \
    --data-seeds "$data" >/dev/null
  cp "$summary/summary.csv" docs/results/composition_summary_partial.csv
fi
python -m pets.compare report >/dev/null
python -m pets.compare report --check
