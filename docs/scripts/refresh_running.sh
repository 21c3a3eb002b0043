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
# The composition study: every finished run of ROOT/composition/results and its data sets' levels (a remade data
# set's runs replace the withdrawn ones: docs/studies/composition.md, amendment of 2026-11-28 21:30 UTC); the
# report makes its summary, primary and secondary files from them.
if compgen -G "$root/composition/results/runs/*/eval.json" >/dev/null; then
  python docs/scripts/partial_offline_runs.py "$root/composition/results" docs/results/composition_runs.csv \
    --levels docs/results/composition_levels.csv >/dev/null
fi
python -m pets.compare report >/dev/null
python -m pets.compare report --check
