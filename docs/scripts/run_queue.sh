#!/usr/bin/env bash
# Run a study's jobs one after another, each resumable, on one core (one thread per process):
#     bash docs/scripts/run_queue.sh JOBFILE [--after PATTERN]
# --after PATTERN: first wait until no process matches PATTERN (pgrep -f; write its first character as [x] so
# that this command's own line does not match it). Each JOBFILE line is "WORKDIR|OUT|KIND|ARGS" (# comments):
#   pets  python run_pets.py ARGS --out OUT, or --resume OUT where OUT has a checkpoint (a finished run exits);
#   sac   python -m pets.collect ARGS --out OUT.npz, skipped where OUT.npz exists (it resumes from its own
#         checkpoint). Each process's CPU seconds (user + system) are appended to OUT.segments after a "start"
#         line; when the collection ends, their sum is written to OUT.cpu_s (read by pets.experiments.gate --sac)
#         only if every started segment was measured (a segment killed with this queue leaves none: unknown);
#   cmd   the shell command ARGS; on exit status 0, OUT.done is written and the job is skipped from then on
#         (a command stopped before it finished runs again, so it should resume by itself, e.g.
#         pets.compare offline into the same --out).
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
TIMEFORMAT='%U %S'  # bash's time keyword: the user and system CPU seconds of the command and its children
while IFS='|' read -r wd out kind args; do
  [[ -z "$wd" || "$wd" == \#* ]] && continue
  log=$logs/$(basename "$out").log
  cd "$wd" || continue
  case $kind in  # skip what is already done
    pets) ;;
    sac) [[ -f "$out.npz" ]] && continue ;;
    cmd) [[ -f "$out.done" ]] && continue ;;
    *) echo "unknown kind '$kind' in $jobs (pets, sac or cmd)" >> "$log"; continue ;;
  esac
  echo "$(date -u +%FT%H:%M) start $out" >> "$logs/queue_$(basename "$jobs").log"
  case $kind in
    pets)
      if [[ -f "$out/checkpoint.pt" ]]; then python run_pets.py --resume "$out" --quiet >> "$log" 2>&1
      else python run_pets.py $args --out "$out" --quiet >> "$log" 2>&1; fi
      rc=$? ;;
    sac)
      echo start >> "$out.segments"
      { time python -m pets.collect $args --out "$out.npz" --quiet >> "$log" 2>&1; } 2> "$out.time"
      rc=$?
      awk 'NF == 2 {print $1 + $2}' "$out.time" >> "$out.segments"
      if ((rc == 0)); then
        total=$(awk '/^start/ {n++; next} {m++; s += $1} END {if (n == m) print s}' "$out.segments")
        [[ -n $total ]] && echo "$total" > "$out.cpu_s"
      fi ;;
    cmd)
      eval "$args" >> "$log" 2>&1
      rc=$?
      ((rc == 0)) && touch "$out.done" ;;
  esac
  echo "$(date -u +%FT%H:%M) end $out rc=$rc" >> "$logs/queue_$(basename "$jobs").log"
done < "$jobs"
