#!/usr/bin/env bash
# The decisive run of the published-curve rung (EXPERIMENTS.md#the-verdict-rule): N seeds of our DrQ (with
# --sear, N of SEAR after them) on cartpole-balance_sparse with DrQ-v2's configuration (EXPERIMENTS.md,
# Rung PC) to F frames,
# one sear.py process per seed (--threads 1, CUDA when torch sees it), as many at a time as the CPU cores and
# the GPU's memory allow, inside a wall-clock budget; then the rung's rule (benchmarks/published_curve.py) on
# what they reached, into one summary.md and its figure.
#
#   benchmarks/gpu_campaign.sh [--seeds N] [--frames F] [--budget-minutes M] [--sear] [--out DIR]
#                              [--render-quality paper|fast] [--eval-every FRAMES]
#   benchmarks/gpu_campaign.sh --quick     2 seeds of tiny networks for 200 frames on the CPU (CI, so it cannot rot)
#
# Defaults: 16 seeds, 40000 frames, 9 minutes (EXPERIMENTS.md#the-gpu-campaign: what is measured, what is
# assumed). --eval-every 20000 evaluates where the published curve has points (the rule reads 20k and 40k);
# evaluations take no part in training (the same train.csv at any spacing), and at 10000, DrQ-v2's, they
# would add 10 of every 45 rendered steps. At the budget's end (less the time to stop and to apply the rule)
# each run still going gets a SIGTERM: sear.py stops at its next episode end with a snapshot (a second one,
# 20 s later, stops it at once); the summary names the seeds that did not reach F, and the rule leaves them
# out. Seeds are started while the time left exceeds the wall time of the slowest seed finished so far.
# Nothing outlives the script: an exit, Ctrl-C or SIGTERM stops every run it started.
# Writes DIR (default runs/gpu_campaign-<UTC time>[-quick]; never an existing one): summary.md, published_curve.png,
# runs/<method>-<seed>/ (the run dirs), logs/. Exit status: 0 when every run ended as planned (F reached or
# stopped by the budget) and the rule ran, 1 otherwise, 2 for bad arguments.
set -uo pipefail
cd "$(dirname "$0")/.."
die() { echo "gpu_campaign.sh: error: $*" >&2; exit 2; }
quick=0 seeds="" frames="" budget="" sear=0 out="" quality="" eval_every=""
while [ $# -gt 0 ]; do
  case $1 in
    --quick) quick=1 ;;
    --sear) sear=1 ;;
    --seeds|--frames|--budget-minutes|--out|--render-quality|--eval-every)
      [ $# -ge 2 ] || die "$1 needs a value"
      case $1 in
        --seeds) seeds=$2 ;; --frames) frames=$2 ;; --budget-minutes) budget=$2 ;; --out) out=$2 ;;
        --render-quality) quality=$2 ;; --eval-every) eval_every=$2 ;;
      esac
      shift ;;
    *) die "unknown argument $1 (use --quick, --seeds N, --frames F, --budget-minutes M, --sear, --out DIR," \
           "--render-quality paper|fast, --eval-every FRAMES)" ;;
  esac
  shift
done
if [ $quick = 1 ]; then
  seeds=${seeds:-2} frames=${frames:-200} budget=${budget:-3} quality=${quality:-fast}
  [[ $frames =~ ^[1-9][0-9]*$ ]] && eval_every=${eval_every:-$(( frames > 1 ? frames / 2 : 1 ))}
else
  seeds=${seeds:-16} frames=${frames:-40000} budget=${budget:-9} eval_every=${eval_every:-20000} quality=${quality:-paper}
fi
[[ $seeds =~ ^[1-9][0-9]*$ ]] || die "--seeds must be a positive integer, got '$seeds'"
[[ $frames =~ ^[1-9][0-9]*$ ]] || die "--frames must be a positive integer, got '$frames'"
[[ $eval_every =~ ^[1-9][0-9]*$ ]] || die "--eval-every must be a positive integer, got '$eval_every'"
[[ $budget =~ ^([0-9]+\.?[0-9]*|\.[0-9]+)$ ]] && [ "$(awk "BEGIN{print ($budget > 0)}")" = 1 ] \
  || die "--budget-minutes must be a positive number, got '$budget'"
[ "$quality" = paper ] || [ "$quality" = fast ] || die "--render-quality must be paper or fast, got '$quality'"
py=${PYTHON:-$(command -v python || command -v python3)}
[ -n "$py" ] || die "no python on PATH (set PYTHON)"
out=${out:-runs/gpu_campaign-$(date -u +%Y%m%d-%H%M%S)$([ $quick = 1 ] && echo -quick)}
[ -e "$out" ] && die "$out exists; give another --out"

# Each run: one torch thread, one llvmpipe thread where EGL renders in software; EGL draws on the GPU where its
# driver provides it (the summary names the renderer).
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 LP_NUM_THREADS=1
start=$SECONDS
budget_s=$(awk "BEGIN{printf \"%d\", $budget * 60}")
grace=20 reserve=$([ $quick = 1 ] && echo 15 || echo 45)  # the stop (grace + 5 s) and the rule after it
stop_at=$((start + budget_s - reserve))
mkdir -p "$out/logs" "$out/runs" || die "cannot make $out"
summary=$out/summary.md

declare -A pid_of=() status_of=() began_of=() wall_of=()
monitor=""
stop_runs() {  # SIGTERM every run still going: a stop at its next episode end; again after $1 s; then SIGKILL
  local job left=()
  for job in "${!pid_of[@]}"; do kill -TERM "${pid_of[$job]}" 2>/dev/null && left+=("$job"); done
  for wait_s in "$1" 5; do
    local deadline=$((SECONDS + wait_s))
    while [ $SECONDS -lt "$deadline" ]; do
      local any=0
      for job in "${left[@]}"; do kill -0 "${pid_of[$job]}" 2>/dev/null && any=1; done
      [ $any = 0 ] && break
      sleep 1
    done
    for job in "${left[@]}"; do kill -"$([ "$wait_s" = 5 ] && echo KILL || echo TERM)" "${pid_of[$job]}" 2>/dev/null; done
  done
}
cleanup() {
  trap - EXIT INT TERM
  [ ${#pid_of[@]} -gt 0 ] && stop_runs 10
  [ -n "$monitor" ] && kill "$monitor" 2>/dev/null
  wait 2>/dev/null
}
trap cleanup EXIT
trap 'echo "gpu_campaign.sh: interrupted: stopping the runs" >&2; cleanup; exit 130' INT
trap 'echo "gpu_campaign.sh: SIGTERM: stopping the runs" >&2; cleanup; exit 143' TERM

# The machine: device, the GPU's free memory, and which renderer draws the env (a failure here stops
# everything before 16 runs fail one by one).
read -r device free_gib gpu_name torch_version < <("$py" - <<'EOF'
import torch
cuda = torch.cuda.is_available()
free = torch.cuda.mem_get_info()[0] / 2**30 if cuda else 0
print("cuda" if cuda else "cpu", f"{free:.0f}", (torch.cuda.get_device_name() if cuda else "none").replace(" ", "_"),
      torch.__version__)
EOF
)
[ -n "${device:-}" ] || { echo "gpu_campaign.sh: error: $py cannot import torch" >&2; exit 1; }
"$py" - "$quality" "$([ $quick = 1 ] && echo 3 || echo 200)" > "$out/logs/env_probe.log" 2>&1 <<'EOF'
import sys, time
sys.path.insert(0, "benchmarks")
import numpy as np, bench_envs, envs
env = envs.make_env("cartpole-balance_sparse", render_quality=sys.argv[1], render_mask=False)
steps = int(sys.argv[2])
wall = bench_envs.steps_per_second(env, steps, np.random.default_rng(0))
cpu = bench_envs.steps_per_second(env, steps, np.random.default_rng(1), time.process_time)
print(f"env: {bench_envs.gl_renderer(env)}; cartpole-balance_sparse, render {sys.argv[1]}: {wall:.0f} agent steps "
      f"per wall second, {cpu:.0f} per CPU-second ({steps} steps, one process)")
EOF
[ $? = 0 ] || { echo "gpu_campaign.sh: error: the env does not render with MUJOCO_GL=$MUJOCO_GL" \
                      "(see $out/logs/env_probe.log)" >&2; exit 1; }

jobs=()
for s in $(seq 1 "$seeds"); do jobs+=("drq-$s"); done
[ $sear = 1 ] && for s in $(seq 1 "$seeds"); do jobs+=("sear-$s"); done
cores=$(nproc)
# assumed (EXPERIMENTS.md#the-gpu-campaign); the summary gives the GPU memory the runs used
gib_per_run=${GIB_PER_RUN:-4}
slots=$(( ${#jobs[@]} < cores ? ${#jobs[@]} : cores ))
if [ "$device" = cuda ]; then
  by_memory=$(( free_gib / gib_per_run ))
  [ "$by_memory" -lt "$slots" ] && slots=$by_memory
  [ "$slots" -ge 1 ] || { echo "gpu_campaign.sh: error: $free_gib GiB free on the GPU, $gib_per_run per run" >&2; exit 1; }
  if command -v nvidia-smi > /dev/null; then
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader,nounits -l 5 > "$out/logs/gpu.csv" 2>&1 &
    monitor=$!
  fi
fi

# The rung's command (EXPERIMENTS.md, Rung PC), without --save-buffer: no run here is resumed.
rung=(--env cartpole-balance_sparse --frames "$frames" --action-repeat 2 --frame-stack 3 --batch-size 256 --lr 1e-4
      --nstep 3 --discount 0.99 --std-start 1.0 --std-end 0.1 --std-steps 100000 --std-clip 0.3 --seed-frames 4000
      --exploration-steps 2000 --update-every 2 --critic-tau 0.01 --feature-dim 50 --hidden-dim 1024
      --replay-size 1000000 --eval-every "$eval_every" --eval-episodes 10 --precision fp32
      --render-quality "$quality" --threads 1 --device "$device")
[ $quick = 1 ] && rung+=(--seed-frames 80 --exploration-steps 40 --max-episode-steps 25 --batch-size 8
                         --feature-dim 16 --hidden-dim 32 --latent-dim 64 --replay-size 1000 --eval-episodes 2)

slowest=0
next=0
while :; do
  for job in "${!pid_of[@]}"; do  # reap the runs that ended
    kill -0 "${pid_of[$job]}" 2>/dev/null && continue
    wait "${pid_of[$job]}"
    status_of[$job]=$?
    wall_of[$job]=$((SECONDS - began_of[$job]))
    [ "${wall_of[$job]}" -gt $slowest ] && slowest=${wall_of[$job]}
    unset "pid_of[$job]"
  done
  left=$((stop_at - SECONDS))
  if [ $left -le 0 ]; then
    [ ${#pid_of[@]} -gt 0 ] && stop_runs $grace
    for job in "${!pid_of[@]}"; do  # 143: stopped by the SIGTERM (137: by the SIGKILL); 0: it ended first
      wait "${pid_of[$job]}"
      status_of[$job]=$?
      case ${status_of[$job]} in 143|137) status_of[$job]=stopped ;; esac
      wall_of[$job]=$((SECONDS - began_of[$job]))
      unset "pid_of[$job]"
    done
    break
  fi
  while [ ${#pid_of[@]} -lt "$slots" ] && [ $next -lt ${#jobs[@]} ] && [ $left -gt $slowest ]; do
    job=${jobs[$next]}
    next=$((next + 1))
    "$py" sear.py "${rung[@]}" --method "${job%-*}" --seed "${job##*-}" --run-root "$out/runs/$job" \
      > "$out/logs/$job.log" 2>&1 &
    pid_of[$job]=$!
    began_of[$job]=$SECONDS
  done
  [ ${#pid_of[@]} = 0 ] && break
  sleep 1
done
trained=$((SECONDS - start))
[ -n "$monitor" ] && kill "$monitor" 2>/dev/null && monitor=""

methods=(drq)
[ $sear = 1 ] && methods+=(sear)
rule=("$py" benchmarks/published_curve.py "$out/runs" --methods "${methods[@]}" --seeds $(seq 1 "$seeds")
      --frames $(seq 0 "$eval_every" "$frames") --out "$out/published_curve.png")
[ $quick = 1 ] && rule+=(--rule-frames "$eval_every" $((2 * eval_every)))  # a reduced run: the pipeline
rule_status=0
if compgen -G "$out/runs/*/*/config.json" > /dev/null; then
  "${rule[@]}" > "$out/logs/published_curve.log" 2>&1
  rule_status=$?
else  # every run stopped before it made its run dir
  echo "no run has a run directory: nothing to apply the rule to" > "$out/logs/published_curve.log"
fi

{
  echo "# gpu_campaign.sh$([ $quick = 1 ] && echo " --quick") ($(date -u +%Y-%m-%dT%H:%M:%SZ))"
  echo
  echo "commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown), host $(hostname), device $device" \
       "($([ "$device" = cuda ] && echo "${gpu_name//_/ }, $free_gib GiB free at the start" || echo "no CUDA device"))," \
       "torch $torch_version, $cores CPU cores, MUJOCO_GL=$MUJOCO_GL"
  tail -n 1 "$out/logs/env_probe.log"
  if [ "$device" = cuda ] && [ "$quality" = paper ] && grep -q llvmpipe "$out/logs/env_probe.log"; then
    echo "(EGL renders on the CPU here, not on the GPU: paper frames then cost ~20 ms of a core each, and 16 seeds" \
         "to 40k frames do not fit 9 minutes; EXPERIMENTS.md#the-gpu-campaign)"
  fi
  echo
  echo "$seeds seeds of ${methods[*]} to $frames frames (evaluations every $eval_every), render $quality;" \
       "$slots at a time (cores $cores$([ "$device" = cuda ] && echo ", GPU memory at $gib_per_run GiB per run"));" \
       "budget $budget_s s, runs stopped from $((stop_at - start)) s"
  echo
  for job in "${jobs[@]}"; do echo "$job ${status_of[$job]:-not_started} ${wall_of[$job]:-}"; done > "$out/logs/status.txt"
  "$py" - "$out" "$frames" <<'EOF'
import csv, glob, sys
out, frames = sys.argv[1], int(sys.argv[2])
print("| run | status | frames reached | wall time | frames/s |\n|---|---|---|---|---|")
for line in open(f"{out}/logs/status.txt"):
    job, status, *wall = line.split()
    rows = [r for p in glob.glob(f"{out}/runs/{job}/*/train.csv") for r in csv.DictReader(open(p))]
    reached = max((int(r["frame"]) for r in rows), default=0)
    said = {"0": "reached F", "stopped": "stopped by the budget", "not_started": "not started (budget)"}.get(
        status, f"FAILED (exit {status}: logs/{job}.log)")
    if status == "0" and reached < frames:
        said = f"ended below F (logs/{job}.log)"
    seconds = int(wall[0]) if wall else 0
    print(f"| {job} | {said} | {reached} | {seconds} s | {reached / seconds:.1f} |" if seconds else
          f"| {job} | {said} | {reached} | | |")
EOF
  if [ -s "$out/logs/gpu.csv" ]; then
    awk -F', ' '{u += $1; n++; if ($1 > umax) umax = $1; if ($2 > mmax) mmax = $2}
      END {if (n) printf "\nGPU (nvidia-smi every 5 s, %d samples): utilization mean %.0f%%, max %d%%; memory used max %.1f GiB\n", n, u / n, umax, mmax / 1024}' \
      "$out/logs/gpu.csv"
  fi
  echo
  echo "## The rule: \`${rule[*]}\`$([ $rule_status = 0 ] || echo " FAILED (exit $rule_status)")"
  echo
  cat "$out/logs/published_curve.log"
  echo
  echo "![published curve](published_curve.png)"
  echo
  echo "## total: $((SECONDS - start)) s (training $trained s), budget $budget_s s:" \
       "$([ $((SECONDS - start)) -le "$budget_s" ] && echo within || echo OVER)"
} > "$summary"
cat "$summary"
failed=$rule_status
for job in "${jobs[@]}"; do
  case ${status_of[$job]:-not_started} in 0|stopped|not_started) ;; *) failed=1 ;; esac
done
[ "$failed" = 0 ]
