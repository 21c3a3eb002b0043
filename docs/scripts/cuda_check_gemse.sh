#!/usr/bin/env bash
# CUDA check of gem-se (issue 32): the gem-se and codec tests on every device, training and evaluation on DEV and
# on the CPU, and two short online runs on DEV. DEV=cuda (default) or cpu for a dry run. On a machine without the
# project installed, wheels in .whl/ are installed first (cuda_check_setup.sh) (docs/performance.md, "gem-se on CUDA").
source "$(dirname "$0")/cuda_check_setup.sh"
echo "== pytest (gem-se, codecs: every device; propagation -k cuda)"
timeout 200 python3 -m pytest -q -p no:cacheprovider tests/test_gem_se.py tests/test_gem_codecs.py 2>&1 | tail -4
timeout 100 python3 -m pytest -q -p no:cacheprovider tests/test_propagation.py -k "cuda or real_gaussian" 2>&1 | tail -2
W=/tmp/gpuw; rm -rf $W; mkdir -p $W
echo "== collect, train gem-se on $DEV and cpu, evaluate"
for env in hopper ant; do
  python3 -m pets.collect --env $env --policy random --episodes 6 --max-steps 200 --seed 0 --out $W/$env.npz --quiet >/dev/null
  python3 -m pets.collect --env $env --policy random --episodes 2 --max-steps 200 --seed 1 --out $W/${env}_test.npz --quiet >/dev/null
  for d in $DEV cpu; do
    t0=$SECONDS; python3 -m pets.train --data $W/$env.npz --model gem-se --out $W/${env}_$d --device $d --preset fast --epochs 5 --quiet threads=2 >/dev/null; echo "$env train $d $((SECONDS-t0)) s"
    python3 -m pets.evaluate --run $W/${env}_$d --data $W/${env}_test.npz --horizons 1,10 --device $d --threads 2 --json $OUT/eval_${env}_$d.json >/dev/null && python3 -c "import json,sys;d=json.load(open(sys.argv[1]))['horizons'];print(sys.argv[1].split('/')[-1], {h: {k: round(v, 6) for k, v in r.items() if k in ('standardized_error', 'translation_error', 'rotation_error')} for h, r in d.items()})" $OUT/eval_${env}_$d.json
  done
done
echo "== run_pets gem-se online, $DEV"
for env in hopper ant; do
  t0=$SECONDS; python3 run_pets.py --model gem-se --env $env --device $DEV --trials 2 --seed 0 --preset fast episode_length=50 seed_steps=200 threads=2 --quiet --out $W/online_$env 2>&1 | tail -3; echo "$env run_pets $DEV $((SECONDS-t0)) s"
  tail -2 $W/online_$env/metrics.csv
done
