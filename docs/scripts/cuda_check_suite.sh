#!/usr/bin/env bash
# The whole test suite where torch sees a GPU (a user's GPU machine running the README's test command as its smoke
# test: `device=auto` is CUDA there, and every test parametrised over devices gets its CUDA case), then three CUDA
# paths end to end: the memory check with the GPU's real free memory, `pets.bench --device cuda` naming the GPU, and a
# short run on CUDA resumed after SIGTERM. Without Ray there (tests/test_ray.py is left out) and without imageio's
# ffmpeg plugin (the one MP4 test is left out). EGL's libraries from .gl/ are unpacked first where present (the
# device README). WORKERS (14), SUITE_S (300), TESTS (tests) and DIST (loadfile) size the pytest run (PYTEST=0
# skips it); E2E=0 skips the rest; DEV=cpu: a dry run.
source "$(dirname "$0")/cuda_check_setup.sh"
if [ -d .gl ]; then for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; fi
export MUJOCO_GL=egl
python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null 2>&1 || echo "pip install -e . failed"
python3 -c "import mujoco, gymnasium, omegaconf, rliable; print('mujoco', mujoco.__version__, gymnasium.__version__)"
echo "== the suite, $(nproc) CPUs, ${WORKERS:-14} workers"
t0=$SECONDS
ONLY_HERE=(--ignore=tests/test_ray.py
  --deselect tests/test_runlogs.py::test_one_trial_with_video_1_writes_an_mp4_of_the_episode)
[ "${PYTEST:-1}" = 1 ] && timeout "${SUITE_S:-300}" python3 -m pytest -q -p no:cacheprovider -n "${WORKERS:-14}" \
  --dist "${DIST:-loadfile}" ${TESTS:-tests} "${ONLY_HERE[@]}" \
  -rfEs > "$OUT/suite.log" 2>&1
echo "pytest rc=$? $((SECONDS - t0)) s"
grep -E "^(FAILED|ERROR|SKIPPED)" "$OUT/suite.log" | cut -c1-300 | head -40
tail -n 2 "$OUT/suite.log"
[ "${E2E:-1}" = 1 ] || exit 0
W=/tmp/gpuw_suite; rm -rf $W; mkdir -p $W
echo "== memory check with the GPU's own free memory: a run whose training data cannot fit"
python3 run_pets.py --env halfcheetah --device "$DEV" --trials 5800 episode_length=100000 --out $W/huge 2>&1 | tail -2
echo "rc=$? (2 expected); run directory left: $([ -e $W/huge ] && echo yes || echo no)"
echo "== pets.bench on $DEV"
timeout 90 python3 -m pets.bench --env halfcheetah --model gem --preset fast --device "$DEV" --repeats 3 \
  --json $W/bench.json 2>&1 | tail -6
python3 -c "import json,sys; m=json.load(open(sys.argv[1]))['machine']; print('machine:', m)" $W/bench.json
echo "== a short run on $DEV, SIGTERM after its first trial, then --resume, against the uninterrupted run"
args=(--env halfcheetah --model gem --preset fast --device "$DEV" --trials 3 --seed 1 --quiet
  episode_length=100 model.max_epochs=5)
timeout 90 python3 run_pets.py "${args[@]}" --out $W/whole
python3 run_pets.py "${args[@]}" --out $W/cut > $W/cut.log 2>&1 &
pid=$!
for _ in $(seq 900); do [ -f $W/cut/metrics.csv ] && [ "$(wc -l < $W/cut/metrics.csv)" -ge 2 ] && break; sleep 0.1; done
kill -TERM $pid; wait $pid; echo "after SIGTERM rc=$? (143 expected): $(tail -n 1 $W/cut.log | cut -c1-200)"
timeout 90 python3 run_pets.py --resume $W/cut --quiet
python3 - $W <<'PY'
import csv, sys
rows = {r: [(x["episode_reward"], x["model_val_loss"]) for x in csv.DictReader(open(f"{sys.argv[1]}/{r}/metrics.csv"))]
        for r in ("whole", "cut")}
same = rows["whole"] == rows["cut"]
print("resumed run's metrics equal the uninterrupted run's:", same, rows["whole"][-1], rows["cut"][-1])
PY
