#!/usr/bin/env bash
# The decisive run of the published-curve rung (EXPERIMENTS.md#the-verdict-rule), in parts that fit one device command each:
# seeds K..K+N-1 of our DrQ (with --sear, the same seeds of SEAR after them) on cartpole-balance_sparse with
# DrQ-v2's configuration (EXPERIMENTS.md, Rung PC) to F frames, one sear.py process per seed, P at a time
# (each with cores / P torch threads, CUDA when torch sees it), inside a wall-clock budget; then the rung's
# rule (benchmarks/published_curve.py) on this part's seeds into summary.md, its figure, and results.csv (the
# part's evaluations and settings, the format of benchmarks/published_curve_results.csv). The rule on the
# union of the parts is published_curve.py with --results once per part: it refuses parts that share a seed
# or ran different settings.
#
#   benchmarks/gpu_campaign.sh [--first-seed K] [--seeds N] [--frames F] [--budget-minutes M] [--parallel P]
#                              [--sear] [--processes] [--out DIR] [--copy-to DIR] [--render-quality paper|fast]
#                              [--eval-every FRAMES] [--official DRQV2_CHECKOUT]
#   benchmarks/gpu_campaign.sh --seeds 16   the campaign in one command: all 16 seeds in one sear.py --seeds group
#   benchmarks/gpu_campaign.sh --seeds 16 --official .drqv2   and the official DrQ-v2 code's 16 seeds after them
#   benchmarks/gpu_campaign.sh --quick     2 seeds of tiny networks for 200 frames on the CPU (CI, so it cannot rot)
#
# Two or more seeds run as ONE group (sear.py --seeds K-L, group.py: their networks updated as one batched
# update, their envs in worker processes), with the reference arithmetic (TF32 off, sear.py's default) and a
# replay ring of the frames' steps (it never wraps, as DrQ-v2's 1M one does not in 40k frames: the same
# draws); --processes runs one sear.py per seed instead, P at a time (how parts 1 and later ran).
#
# Defaults: seeds 1-4, 40000 frames, 4 at a time, 9 minutes. Sizing (measured on an H200 machine: 16
# cores, EGL drawing on the GPU; docs/published-curve.md#the-gpu-campaign): four DrQ runs at once make ~100-108
# frames/s each (~413 together), so a seed's 40k frames take 370-400 s, and its evaluations at 0, 20k and
# 40k (10 episodes of 500 agent steps each, 15,000 steps at ~900 steps/s) ~17 s more: ~390-417 s, under the
# 495 s the runs get (9 minutes less the 45 s reserve), inside one 10-minute device command. All 16 seeds the
# rule needs for MATCH do not fit one: 640k frames at ~413 frames/s is ~26 minutes. So they are 4 parts,
# --first-seed 1, 5, 9 and 13, one per loan of the machine (15 minutes with its start: a second part does not
# fit). --sear doubles a part's runs: with --seeds 2, DrQ and SEAR seeds K, K+1 run at once. --copy-to DIR (a
# folder that outlives the machine) gets the part's 4 small files (seeds<K>-<L>_summary.md, _results.csv,
# _curve.png, _logs.tar.gz: logs and the run dirs without snapshots).
# --eval-every 20000 evaluates where the rule reads (20k and 40k); evaluations take no part in training (the
# same train.csv at any spacing), and at 10000, DrQ-v2's, they would add 10 of every 45 rendered steps. At the
# budget's end (less the time to stop and to apply the rule) each run still going gets a SIGTERM: sear.py
# stops at its next episode end with a snapshot (a second one, 20 s later, stops it at once); the summary
# names the seeds that did not reach F, and the rule leaves them out. Seeds are started while the time left
# exceeds the wall time of the slowest seed finished so far. Nothing outlives the script: an exit, Ctrl-C or
# SIGTERM stops every run it started.
# --official DIR (a checkout of facebookresearch/drqv2): when our runs have ended, the official code's train.py on
# the same seeds (benchmarks/run_official.py: the code unmodified, today's stack adapted from outside, TF32 off), P
# at a time while the budget lasts (the same start rule), each as runs/official-<seed>/ (its hydra run dir); the
# rule reads them as one more method, "drqv2 official". After ours, not beside them: they would share the cores
# and the GPU with our group, whose speed the budget was sized by. Their settings are the released config's but
# for the budget and evaluations, ours: num_train_frames F + 2 (so that it evaluates at F), eval_every_frames,
# num_eval_episodes; it renders with physics.render at 84x84 whatever --render-quality says (it has no 'fast').
# The budget's SIGTERM ends a run at once (it has no safe stop): a cut run's eval.csv rows stand. The summary
# names the official seeds the budget left unstarted. --quick with --official: a 6-minute budget by default.
# The GPU machine has no package index: the checkout travels as an ignored folder, and hydra's packages (pure
# Python but PyYAML, whose wheel must be for the GPU machine's Python) as wheels built where there is an index:
#   git clone https://github.com/facebookresearch/drqv2 .drqv2 && git -C .drqv2 checkout c0c650b
#   python -m pip wheel --no-deps -w .wheels hydra-core==1.3.2 omegaconf==2.3.0 antlr4-python3-runtime==4.9.3 \
#       hydra-submitit-launcher==1.2.0 PyYAML
#   printf '.drqv2/\n.wheels/\n' >> .git/info/exclude              # neither is committed
#   then on the GPU machine: python -m pip install --no-deps --no-index .wheels/*.whl
# Writes DIR (default runs/gpu_campaign-<UTC time>[-quick]; never an existing one): summary.md, results.csv,
# published_curve.png, runs/<method>-<seed>/ (the run dirs), logs/. Exit status: 0 when every run ended as
# planned (F reached or stopped by the budget) and the rule ran, 1 otherwise, 2 for bad arguments.
set -uo pipefail
cd "$(dirname "$0")/.."
die() { echo "gpu_campaign.sh: error: $*" >&2; exit 2; }
same=() quick=0 first=1 seeds="" frames="" budget="" parallel=4 sear=0 out="" copy_to="" quality="" eval_every=""
processes=0 official=""
while [ $# -gt 0 ]; do
  case $1 in
    --quick) quick=1 same+=("$1") ;;
    --sear) sear=1 same+=("$1") ;;
    --processes) processes=1 same+=("$1") ;;
    --first-seed|--seeds|--frames|--budget-minutes|--parallel|--out|--copy-to|--render-quality|--eval-every|--official)
      [ $# -ge 2 ] || die "$1 needs a value"
      case $1 in
        --first-seed) first=$2 ;; --seeds) seeds=$2 ;; --frames) frames=$2 ;; --budget-minutes) budget=$2 ;;
        --parallel) parallel=$2 ;; --out) out=$2 ;; --copy-to) copy_to=$2 ;; --render-quality) quality=$2 ;;
        --eval-every) eval_every=$2 ;; --official) official=$2 ;;
      esac
      case $1 in --first-seed|--out|--copy-to) ;; *) same+=("$1" "$2") ;; esac  # what the next part repeats
      shift ;;
    *) die "unknown argument $1 (use --quick, --first-seed K, --seeds N, --frames F, --budget-minutes M," \
           "--parallel P, --sear, --processes, --out DIR, --copy-to DIR, --render-quality paper|fast, --eval-every FRAMES," \
           "--official DRQV2_CHECKOUT)" ;;
  esac
  shift
done
if [ $quick = 1 ]; then
  # the official code's evaluations are 500 agent steps an episode, rendered at 84x84, even here
  seeds=${seeds:-2} frames=${frames:-200} budget=${budget:-$([ -n "$official" ] && echo 6 || echo 3)} quality=${quality:-fast}
  [[ $frames =~ ^[1-9][0-9]*$ ]] && eval_every=${eval_every:-$(( frames > 1 ? frames / 2 : 1 ))}
else
  seeds=${seeds:-4} frames=${frames:-40000} budget=${budget:-9} eval_every=${eval_every:-20000} quality=${quality:-paper}
fi
[[ $first =~ ^[1-9][0-9]*$ ]] || die "--first-seed must be a positive integer, got '$first'"
[[ $seeds =~ ^[1-9][0-9]*$ ]] || die "--seeds must be a positive integer, got '$seeds'"
[[ $parallel =~ ^[1-9][0-9]*$ ]] || die "--parallel must be a positive integer, got '$parallel'"
[[ $frames =~ ^[1-9][0-9]*$ ]] || die "--frames must be a positive integer, got '$frames'"
[[ $eval_every =~ ^[1-9][0-9]*$ ]] || die "--eval-every must be a positive integer, got '$eval_every'"
[[ $budget =~ ^([0-9]+\.?[0-9]*|\.[0-9]+)$ ]] && [ "$(awk "BEGIN{print ($budget > 0)}")" = 1 ] \
  || die "--budget-minutes must be a positive number, got '$budget'"
[ "$quality" = paper ] || [ "$quality" = fast ] || die "--render-quality must be paper or fast, got '$quality'"
py=${PYTHON:-$(command -v python || command -v python3)}
[ -n "$py" ] || die "no python on PATH (set PYTHON)"
if [ -n "$official" ]; then  # the checkout and hydra, before anything runs (run_official.py's one-line error)
  why=$("$py" benchmarks/run_official.py --official "$official" --check 2>&1) || die "${why#run_official.py: error: }"
fi
out=${out:-runs/gpu_campaign-$(date -u +%Y%m%d-%H%M%S)$([ $quick = 1 ] && echo -quick)}
[ -e "$out" ] && die "$out exists; give another --out"
last=$((first + seeds - 1))
part=seeds$first-$last  # the part's name in --copy-to
if [ -n "$copy_to" ]; then
  mkdir -p "$copy_to" 2>/dev/null && [ -w "$copy_to" ] || die "--copy-to $copy_to: cannot write there"
  for f in summary.md results.csv curve.png logs.tar.gz; do
    [ -e "$copy_to/${part}_$f" ] && die "$copy_to/${part}_$f exists; give another --copy-to"
  done
fi

# Each run: --threads torch threads (set below), one OpenMP thread elsewhere, one llvmpipe thread where EGL
# renders in software; EGL draws on the GPU where its driver provides it (the summary names the renderer).
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

group=$([ $processes = 0 ] && [ "$seeds" -ge 2 ] && echo 1 || echo 0)  # one group per method, or a process per seed
jobs=()
if [ $group = 1 ]; then
  jobs+=(drq-group)
  [ $sear = 1 ] && jobs+=(sear-group)
else
  for s in $(seq "$first" "$last"); do jobs+=("drq-$s"); done
  [ $sear = 1 ] && for s in $(seq "$first" "$last"); do jobs+=("sear-$s"); done
fi
# The cores this process may use (its CPU affinity). Not plain `nproc`: it honours OMP_NUM_THREADS, which this
# script set to 1 above for the runs' other threads, and so counted 1 core on the 16-core machine.
cores=$(env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc)
# assumed (docs/published-curve.md#the-gpu-campaign); the summary gives the GPU memory the runs used
gib_per_run=${GIB_PER_RUN:-4}
slots=$(( ${#jobs[@]} < cores ? ${#jobs[@]} : cores ))
[ "$parallel" -lt "$slots" ] && slots=$parallel
if [ "$device" = cuda ]; then
  by_memory=$(( free_gib / gib_per_run ))
  [ "$by_memory" -lt "$slots" ] && slots=$by_memory
  [ "$slots" -ge 1 ] || { echo "gpu_campaign.sh: error: $free_gib GiB free on the GPU, $gib_per_run per run" >&2; exit 1; }
  if command -v nvidia-smi > /dev/null; then
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader,nounits -l 5 > "$out/logs/gpu.csv" 2>&1 &
    monitor=$!
  fi
fi
threads=$(( cores / slots ))  # the cores shared out: 4 runs of 4 threads on 16 cores is what was measured
# The official code's seeds (--official): the same seeds, after ours (they would share the cores and the GPU with
# our group and change its speed, which the budget was sized by), P at a time within what is left.
ojobs=()
[ -n "$official" ] && for s in $(seq "$first" "$last"); do ojobs+=("official-$s"); done
oslots=$(( seeds < cores ? seeds : cores ))
[ "$parallel" -lt "$oslots" ] && oslots=$parallel
[ "$device" = cuda ] && [ "$by_memory" -lt "$oslots" ] && oslots=$by_memory
othreads=$(( cores / oslots ))
# a group: its seeds' env workers take most cores, its learner a few (torch threads); its GPU memory grows with them
[ $group = 1 ] && threads=$(( cores > 8 ? 4 : cores ))

# The rung's command (EXPERIMENTS.md, Rung PC), without --save-buffer: no run here is resumed.
eval_episodes=$([ $quick = 1 ] && echo 2 || echo 10)
rung=(--env cartpole-balance_sparse --frames "$frames" --action-repeat 2 --frame-stack 3 --batch-size 256 --lr 1e-4
      --nstep 3 --discount 0.99 --std-start 1.0 --std-end 0.1 --std-steps 100000 --std-clip 0.3 --seed-frames 4000
      --exploration-steps 2000 --update-every 2 --critic-tau 0.01 --feature-dim 50 --hidden-dim 1024
      --replay-size 1000000 --eval-every "$eval_every" --eval-episodes "$eval_episodes" --precision fp32
      --render-quality "$quality" --threads "$threads" --device "$device")
[ $quick = 1 ] && rung+=(--seed-frames 80 --exploration-steps 40 --max-episode-steps 25 --batch-size 8
                         --feature-dim 16 --hidden-dim 32 --latent-dim 64 --replay-size 1000
                         --drop-inapplicable)  # one set for drq and sear: drq has no --latent-dim
# a group's rings: every step of F frames at action repeat 2, and a reset slot per episode (1000 steps a most)
[ $group = 1 ] && [ $quick = 0 ] && rung+=(--replay-size $(( frames / 2 + frames / 500 + 100 )))
# The official code's run of a seed: its config as released (cartpole_balance_sparse: cfgs/task/easy.yaml) but for
# the budget and the evaluations, as ours: F + 2 frames keeps its evaluation at F (it stops before step F / 2 + 1).
# It renders as written (physics.render, 84x84: --render-quality fast does not apply to it); TF32 off.
official_run=(task@_global_=cartpole_balance_sparse "device=$device" save_video=false use_tb=false
              "num_train_frames=$((frames + 2))" "eval_every_frames=$eval_every" "num_eval_episodes=$eval_episodes")

ours_running() {  # whether a run of ours is still going (the official code's wait for them)
  local job
  for job in "${!pid_of[@]}"; do [[ $job == official-* ]] || return 0; done
  return 1
}
start_runs() {  # ours while the time left ($1) exceeds the slowest run of ours so far; then the official code's
  local job who
  while [ ${#pid_of[@]} -lt "$slots" ] && [ $next -lt ${#jobs[@]} ] && [ "$1" -gt $slowest ]; do
    job=${jobs[$next]}
    next=$((next + 1))
    if [ $group = 1 ]; then who=(--seeds "$first-$last"); else who=(--seed "${job##*-}"); fi
    "$py" sear.py "${rung[@]}" --method "${job%-*}" "${who[@]}" --run-root "$out/runs/$job" \
      > "$out/logs/$job.log" 2>&1 &
    pid_of[$job]=$!
    began_of[$job]=$SECONDS
  done
  [ $next -lt ${#jobs[@]} ] || ours_running && return
  while [ ${#pid_of[@]} -lt "$oslots" ] && [ $onext -lt ${#ojobs[@]} ] && [ "$1" -gt $oslowest ]; do
    job=${ojobs[$onext]}
    onext=$((onext + 1))
    OMP_NUM_THREADS=$othreads "$py" benchmarks/run_official.py --official "$official" -- "${official_run[@]}" \
      "seed=${job#official-}" "hydra.run.dir='$out/runs/$job'" > "$out/logs/$job.log" 2>&1 &
    pid_of[$job]=$!
    began_of[$job]=$SECONDS
  done
}

slowest=0 oslowest=0  # the wall time of the slowest run finished so far: ours, the official code's
next=0 onext=0
while :; do
  for job in "${!pid_of[@]}"; do  # reap the runs that ended
    kill -0 "${pid_of[$job]}" 2>/dev/null && continue
    wait "${pid_of[$job]}"
    status_of[$job]=$?
    wall_of[$job]=$((SECONDS - began_of[$job]))
    if [[ $job == official-* ]]; then [ "${wall_of[$job]}" -gt $oslowest ] && oslowest=${wall_of[$job]}
    else [ "${wall_of[$job]}" -gt $slowest ] && slowest=${wall_of[$job]}; fi
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
  start_runs $left
  [ ${#pid_of[@]} = 0 ] && break
  sleep 1
done
trained=$((SECONDS - start))
[ -n "$monitor" ] && kill "$monitor" 2>/dev/null && monitor=""

methods=(drq)
[ $sear = 1 ] && methods+=(sear)
rule=("$py" benchmarks/published_curve.py "$out/runs" --methods "${methods[@]}" --seeds $(seq "$first" "$last")
      --frames $(seq 0 "$eval_every" "$frames") --out "$out/published_curve.png" --results "$out/results.csv" --record)
[ $quick = 1 ] && rule+=(--rule-frames "$eval_every" $((2 * eval_every)))  # a reduced run: the pipeline
# The official code's runs, one more method: those that made their run dir (hydra's .hydra/config.yaml), as a glob
# where every one did (a cut run's eval.csv rows stand), else by name.
odirs=() oall=1
for d in "$out"/runs/official-*/; do
  [ -d "$d" ] || continue
  if [ -f "$d.hydra/config.yaml" ]; then odirs+=("${d%/}"); else oall=0; fi
done
if [ ${#odirs[@]} -gt 0 ]; then
  if [ $oall = 1 ]; then rule+=(--official "$out/runs/official-*"); else rule+=(--official "${odirs[@]}"); fi
fi
match_seeds=$("$py" -c 'import sys; sys.path.insert(0, "benchmarks"); import published_curve as p; print(p.MATCH_SEEDS)' \
              2>/dev/null || echo 16)  # the seeds the rule needs for MATCH
rule_status=0
if [ -n "$(find "$out/runs" -name config.json -print -quit 2>/dev/null)" ] || [ ${#odirs[@]} -gt 0 ]; then
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
    echo "(EGL renders on the CPU here, not on the GPU: paper frames then cost ~20 ms of a core each, and a seed's" \
         "40k frames do not fit 9 minutes; docs/published-curve.md#the-gpu-campaign)"
  fi
  echo
  if [ $group = 1 ]; then how="one sear.py --seeds $first-$last group per method, $threads torch threads (cores $cores)"
  else how="$slots at a time, $threads torch threads each (cores $cores, --parallel $parallel$(
       [ "$device" = cuda ] && echo ", GPU memory at $gib_per_run GiB per run"))"; fi
  echo "seeds $first-$last of ${methods[*]} to $frames frames (evaluations every $eval_every), render $quality;" \
       "$how; budget $budget_s s, runs stopped from $((stop_at - start)) s"
  if [ -n "$official" ]; then
    echo
    echo "then the official code on seeds $first-$last (facebookresearch/drqv2" \
         "$(git -C "$official" rev-parse --short HEAD 2>/dev/null || echo "of unknown commit"), its train.py unmodified" \
         "through benchmarks/run_official.py, TF32 off), $oslots at a time (torch threads: $othreads each) after ours:" \
         "${official_run[*]}; rendered as written (physics.render, 84x84), whatever --render-quality says"
    unstarted=()
    for job in "${ojobs[@]}"; do [ -z "${status_of[$job]:-}" ] && unstarted+=("${job#official-}"); done
    [ ${#unstarted[@]} -gt 0 ] && echo "official seeds not started (the budget was spent first): ${unstarted[*]}"
  fi
  echo
  for job in "${jobs[@]}" "${ojobs[@]}"; do echo "$job ${status_of[$job]:-not_started} ${wall_of[$job]:-}"; done > "$out/logs/status.txt"
  "$py" - "$out" "$frames" <<'EOF'
import csv, glob, json, os, sys
out, frames = sys.argv[1], int(sys.argv[2])
print("| run | status | frames reached | wall time | frames/s |\n|---|---|---|---|---|")
for line in open(f"{out}/logs/status.txt"):
    job, status, *wall = line.split()
    said = {"0": "reached F", "stopped": "stopped by the budget", "not_started": "not started (budget)"}.get(
        status, f"FAILED (exit {status}: logs/{job}.log)")
    seconds = int(wall[0]) if wall else 0
    # a run: runs/<job>/<run dir>; a group: runs/<job>/<group dir>/<each seed's run dir>, frames/s of all of them
    paths = sorted(glob.glob(f"{out}/runs/{job}/*/train.csv") or glob.glob(f"{out}/runs/{job}/*/*/train.csv"))
    reached = [max((int(r["frame"]) for r in csv.DictReader(open(p))), default=0) for p in paths] or [0]
    if job.startswith("official-"):  # its hydra run dir; it logs training at episode ends (1000 frames), and its
        # evaluations at their frames: the last of either is how far it got
        paths = [p for p in (f"{out}/runs/{job}/train.csv", f"{out}/runs/{job}/eval.csv") if os.path.exists(p)]
        reached = [max((int(float(r["frame"])) for p in paths for r in csv.DictReader(open(p))), default=0)]
        paths = paths[:1]  # one seed
    if status == "0" and min(reached) < frames:
        said = f"ended below F (logs/{job}.log)"
    seeds = f" ({len(paths)} seeds)" if len(paths) > 1 else ""
    print(f"| {job}{seeds} | {said} | {min(reached)} | {seconds} s | {sum(reached) / seconds:.1f} |" if seconds else
          f"| {job}{seeds} | {said} | {min(reached)} | | |")
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
  echo "## The campaign: this part and the next"
  echo
  echo "This part holds seeds $first-$last ($seeds of the $match_seeds that MATCH needs: the verdict above counts" \
       "this part alone). Its evaluations and settings: results.csv$([ -n "$copy_to" ] && echo " (${part}_results.csv)")."
  echo "The next part (other seeds, the same settings): \`benchmarks/gpu_campaign.sh --first-seed $((last + 1))${same[*]:+ ${same[*]}}\`."
  parts=()  # parts of this size from seed 1 until MATCH's seeds (and this part) are covered
  for ((a = 1; a <= (last > match_seeds ? last : match_seeds); a += seeds)); do
    parts+=(--results "seeds$a-$((a + seeds - 1))_results.csv")
  done
  echo "The rule on the union of the parts (each part's results file once, as --copy-to names it; it refuses a seed" \
       "in two parts and parts of different settings): \`python benchmarks/published_curve.py ${parts[*]}" \
       "--methods ${methods[*]} --seeds \$(seq 1 $((a - 1))) --frames $(seq -s ' ' 0 "$eval_every" "$frames")" \
       "--out published_curve.png\`."
  echo
  echo "## total: $((SECONDS - start)) s (training $trained s), budget $budget_s s:" \
       "$([ $((SECONDS - start)) -le "$budget_s" ] && echo within || echo OVER)"
} > "$summary"
cat "$summary"
if [ -n "$copy_to" ]; then  # the part's small files, for a machine whose disk does not outlive it
  for f in summary.md results.csv; do [ -e "$out/$f" ] && cp "$out/$f" "$copy_to/${part}_$f"; done
  [ -e "$out/published_curve.png" ] && cp "$out/published_curve.png" "$copy_to/${part}_curve.png"
  tar -czf "$copy_to/${part}_logs.tar.gz" -C "$out" --exclude='*.pt' --exclude='*.npz' --exclude='*.mp4' logs runs \
    || echo "gpu_campaign.sh: could not write $copy_to/${part}_logs.tar.gz" >&2
  echo "copied to $copy_to: $(cd "$copy_to" && ls -d "${part}"_* | tr '\n' ' ')"
fi
failed=$rule_status
for job in "${jobs[@]}" "${ojobs[@]}"; do
  case ${status_of[$job]:-not_started} in 0|stopped|not_started) ;; *) failed=1 ;; esac
done
[ "$failed" = 0 ]
