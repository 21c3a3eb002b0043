#!/usr/bin/env bash
# Run a study's jobs one after another, each resumable, on one core (one thread per process):
#     bash docs/scripts/run_queue.sh JOBFILE [--after PATTERN]
# --after PATTERN: first wait until no process matches PATTERN (pgrep -f; write its first character as [x] so
# that this command's own line does not match it). Each JOBFILE line is "WORKDIR|OUT|KIND|ARGS" (# comments):
#   pets  python run_pets.py ARGS --out OUT, or --resume OUT where OUT has a checkpoint (a finished run exits);
#   sac   python -m pets.collect ARGS --out OUT.npz, skipped where OUT.npz exists (it resumes from its own
#         checkpoint); its process CPU seconds written to OUT.cpu_s (read by pets.experiments.gate --sac);
#   cmd   the shell command ARGS (which resumes by itself, e.g. pets.compare offline into the same --out).
# Logs: LOGDIR/NAME.log per job (NAME: OUT's last part) and LOGDIR/queue_JOBFILE.log (LOGDIR: $QUEUE_LOGS, default
# the JOBFILE's directory/logs). Lines are read as the queue reaches them: appending to JOBFILE extends the queue.
set -u
jobs=$(realpath "$1")
if [[ ${2:-} == --after ]]; then
  while pgrep -f "$3" >/dev/null; do sleep 30; done
fi
logs=${QUEUE_LOGS:-$(dirname "$jobs")/logs}
mkdir -p "$logs"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
while IFS='|' read -r wd out kind args; do
  [[ -z "$wd" || "$wd" == \#* ]] && continue
  log=$logs/$(basename "$out").log
  echo "$(date -u +%FT%H:%M) start $out" >> "$logs/queue_$(basename "$jobs").log"
  cd "$wd" || continue
  case $kind in
    pets)
      if [[ -f "$out/checkpoint.pt" ]]; then python run_pets.py --resume "$out" --quiet >> "$log" 2>&1
      else python run_pets.py $args --out "$out" --quiet >> "$log" 2>&1; fi ;;
    sac)
      [[ -f "$out.npz" ]] && continue
      /usr/bin/time -f "%U %S" -o "$out.time" python -m pets.collect $args --out "$out.npz" --quiet >> "$log" 2>&1 \
        && awk '{print $1 + $2}' "$out.time" > "$out.cpu_s" ;;
    cmd) eval "$args" >> "$log" 2>&1 ;;
    *) echo "unknown kind '$kind' in $jobs (pets, sac or cmd)" >> "$log" ;;
  esac
  echo "$(date -u +%FT%H:%M) end $out rc=$?" >> "$logs/queue_$(basename "$jobs").log"
done < "$jobs"
