#!/usr/bin/env bash
# CUDA check of planning with a pre-trained model (issue 38): the planner tests on every device, then open-loop and
# closed-loop planning with frozen models trained on a CPU (RUNS: run directories with checkpoint.pt and
# config.yaml), on DEV and on the CPU, the same seed. DEV=cuda (default) or cpu for a dry run. On a machine without
# the project installed, wheels in .whl/ are installed first (cuda_check_setup.sh) (docs/performance.md).
source "$(dirname "$0")/cuda_check_setup.sh"
RUNS=${RUNS:-results/gpucheck}
FAST="planner.population=100 planner.particles=5 planner.horizon=15 planner.iterations=3 planner.elites=0.1"
echo "== pytest (planners on every device; propagation -k cuda)"
timeout 240 python3 -m pytest -q -p no:cacheprovider tests/test_planners.py 2>&1 | tail -15
timeout 100 python3 -m pytest -q -p no:cacheprovider tests/test_propagation.py -k "cuda" 2>&1 | tail -2
summary='import json,sys; r=json.load(open(sys.argv[1])); t=r["total"]; print(sys.argv[1].split("/")[-1], "device", r["device"], "total", round(t["mean"], 3), "per episode", [round(v, 3) for v in t["values"]])'
for run in "$RUNS"/*/; do
  name=$(basename "$run")
  for d in $DEV cpu; do
    t0=$SECONDS
    python3 -m pets.openloop --run "$run" --planner mppi --episodes 2 --seed 2 --device $d --threads 2 --quiet \
      --json "$OUT/open_${name}_$d.json" >/dev/null && python3 -c "$summary" "$OUT/open_${name}_$d.json"
    echo "$name open loop $d $((SECONDS-t0)) s"
    t0=$SECONDS
    python3 -m pets.openloop --run "$run" --planner mppi --closed-loop --steps 100 --episodes 1 --seed 2 --device $d \
      --threads 2 --quiet --json "$OUT/closed_${name}_$d.json" $FAST >/dev/null && python3 -c "$summary" "$OUT/closed_${name}_$d.json"
    echo "$name closed loop $d $((SECONDS-t0)) s"
  done
done
