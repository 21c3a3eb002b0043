#!/usr/bin/env bash
# CUDA check of the locomotion preset (issue 56) and planner.risk_aversion: the CUDA cases of the suite, then short
# locomotion-preset runs (2,500 env steps: the random seed episodes, two trainings, ~1,500 planned steps) on DEV
# and on the CPU side by side: Ant at pilot v8's settings (horizon 10, no value, risk aversion 1) and HalfCheetah
# with gem at the preset (terminal value on). DEV=cuda (default) or cpu for a dry run. On a machine without the
# project installed, wheels in .whl/ are installed first (cuda_check_setup.sh) (docs/performance.md). STEPS (2500) and
# PYTEST (1; 0 skips the tests) shorten a dry run.
STEPS=${STEPS:-2500}
source "$(dirname "$0")/cuda_check_setup.sh"
echo "== pytest: CUDA cases and risk aversion"
[ "${PYTEST:-1}" = 1 ] && timeout 240 python3 -m pytest -q -p no:cacheprovider -n 8 -k "cuda or risk" tests/test_propagation.py \
  tests/test_planners.py tests/test_lie.py tests/test_precision.py tests/test_gem_se.py tests/test_compiled_training.py \
  2>&1 | tail -3
W=/tmp/gpuw_loco; rm -rf $W; mkdir -p $W
run() {  # ENV HEAD DEVICE EXTRA...
  local env=$1 head=$2 dev=$3; shift 3
  local t0=$SECONDS
  python3 run_pets.py --env $env --model $head --preset locomotion --seed 0 --device $dev --out $W/$env-$head-$dev \
    --quiet threads=1 max_env_steps=$STEPS "$@" > $W/$env-$head-$dev.log 2>&1
  echo "$env $head $dev rc=$? $((SECONDS - t0)) s"
}
echo "== locomotion preset, $DEV and cpu (in parallel)"
run ant delta cpu planner.horizon=10 value.enabled=false planner.risk_aversion=1 &
run halfcheetah gem cpu &
run ant delta $DEV planner.horizon=10 value.enabled=false planner.risk_aversion=1
run halfcheetah gem $DEV
wait
python3 - "$W" <<'PY'
import csv, math, statistics, sys
from pathlib import Path
for run in sorted(Path(sys.argv[1]).glob("*-*-*")):
    if not run.is_dir():
        continue
    rows = list(csv.DictReader(open(run / "metrics.csv")))
    planned = [r for r in rows if float(r["plan_seconds_per_step"] or 0) > 0]
    finite = all(math.isfinite(float(r["episode_reward"])) for r in rows)
    per_step = statistics.median(float(r["plan_seconds_per_step"]) for r in planned) if planned else float("nan")
    print(f"{run.name}: {len(rows)} episodes, env steps {rows[-1]['env_steps']}, rewards finite {finite}, "
          f"median plan s/step {per_step:.4f}, last reward {float(rows[-1]['episode_reward']):.1f}, "
          f"val loss {rows[-1]['model_val_loss']}")
PY
for f in $W/*.log; do grep -i -E "error|warn|nan" $f | head -3; done
