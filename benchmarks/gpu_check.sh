#!/usr/bin/env bash
# What only a GPU can show, in <= 8 minutes on one GPU, into one summary file:
#   tests    the tests that take a device (tests/conftest.py: SEAR_TEST_DEVICE=cuda, `-m device`),
#            and sear.py's smoke run (test_cli.py; sear.py picks CUDA itself with --device auto)
#   counts   ops, host syncs and host->device bytes of one update of every method (update_counts.py;
#            on the GPU the counts of CUDA's path)
#   update   the speed layer's table (bench_speed.py): drq's and sear's plain update at batch 256
#            (s/update, CUDA kernels per update) and each device's gain over it, fp32 and TF32:
#            --cuda-graph, --compile, both, the ring on the GPU against the host's, --prefetch, the
#            seeds' batched update (8 seeds); compile and capture times apart
#   envs     env steps/s with MUJOCO_GL=egl, and which OpenGL renderer drew them (the GPU's, or
#            Mesa's llvmpipe if EGL fell back to software)
#   train-M  a training run of the published-curve rung's command (cartpole-balance_sparse, sear,
#            DrQ-v2's config, EXPERIMENTS.md) per mode M of --runs, RUN_SECONDS each (modes that
#            compile COMPILE_SECONDS more), stopped by Ctrl-C (SIGINT): frames/s after the seed
#            frames. Modes: plain (--cuda-graph off --compile off --replay-device cpu --prefetch
#            off: sear.py's update as written, batches sampled on the host in turn), default
#            (what CUDA runs with no flag: compile, CUDA graph, the ring on the GPU), graph
#            (--compile off --cuda-graph on), compile (--compile on --cuda-graph off), tf32
#            (default + --tf32), bf16 (default + --precision bf16)
#   profile  drq's and sear's plain update at batch 256 through torch.profiler (bench_agent.py
#            --profile): host and wall time, GPU kernel time, kernels launched, host->device bytes,
#            host syncs, the longest kernels
#   split    bench_agent.py: each method's s/update and share of the GPU's fp32 / bf16 GEMM peak
#            measured in the same run, and where a training step's time goes (env / act / sample /
#            update)
#   layouts  channels_last (sear.py's conv layout) against NCHW, s/update (bench_agent.py
#            --compare-layouts)
#
#   benchmarks/gpu_check.sh [--out DIR] [--runs "MODES"] [--skip "STEPS"]   on a machine with CUDA
#   benchmarks/gpu_check.sh --quick        the same steps on the CPU with tiny budgets (CI, so this
#                                          cannot rot)
#
# Steps run in the order above. Each runs under what is left of the 480 s budget: one that would
# start with less than its minimum left is reported as skipped; one that fails (a mode that does not
# compile, say) is reported and the rest still run. --runs defaults to "plain default" on a GPU
# and "plain compile bf16" with --quick. --quick runs a fast subset of the device tests and only
# collects the rest (a test selection that no longer matches anything fails), trains tiny networks
# for a few hundred frames, benchmarks at batch 8, counts tiny networks and skips what needs CUDA
# (TF32, CUDA graphs, the ring on the GPU, the prefetcher, the profile: bench_speed.py's table
# says "needs CUDA" in their cells); on a CPU without native bf16 (bench_agent.native_bf16;
# SEAR_ASSUME_NO_BF16=1 pretends so) it skips the bf16 training run, and bench_agent.py its bf16
# GEMM peak and updates, each with a line saying so: emulated bf16 runs many times slower than fp32.
# Writes DIR (default runs/gpu_check-<UTC time>[-quick]; never an existing one): summary.md, each
# step's log, the training runs. Exit status: 0 when every step that ran passed, 1 otherwise, 2 for
# bad arguments. Needs only requirements.txt's packages (torch 2.11 or later).
set -uo pipefail
cd "$(dirname "$0")/.."
quick=0
out=""
runs=""
skip=""
modes="plain default graph compile tf32 bf16"
steps="tests counts update envs train profile split layouts"
while [ $# -gt 0 ]; do
  case $1 in
    --quick) quick=1 ;;
    --out|--runs|--skip)
      [ $# -ge 2 ] || { echo "gpu_check.sh: error: $1 needs a value" >&2; exit 2; }
      case $1 in --out) out=$2 ;; --runs) runs=$2 ;; --skip) skip=$2 ;; esac
      shift ;;
    *) echo "gpu_check.sh: error: unknown argument $1 (use --quick, --out DIR, --runs MODES," \
            "--skip STEPS)" >&2
       exit 2 ;;
  esac
  shift
done
for m in $runs; do
  [[ " $modes " == *" $m "* ]] ||
    { echo "gpu_check.sh: error: unknown mode $m in --runs (modes: $modes)" >&2; exit 2; }
done
for s in $skip; do
  [[ " $steps " == *" $s "* ]] ||
    { echo "gpu_check.sh: error: unknown step $s in --skip (steps: $steps)" >&2; exit 2; }
done
export MUJOCO_GL=${MUJOCO_GL:-egl}
budget=480
bf16_note=""
if [ $quick = 1 ]; then
  device=cpu; seconds=${RUN_SECONDS:-60}; compile_seconds=${COMPILE_SECONDS:-240}; suffix=-quick
  runs=${runs:-"plain compile bf16"}
  # A CPU that emulates bf16 (no avx512_bf16 / amx_bf16) trains and benchmarks it many times slower
  # than fp32.
  bf16_note=$(python -c "import sys; sys.path.insert(0, 'benchmarks'); import bench_agent
native, why = bench_agent.native_bf16(); print('' if native else why)" 2>/dev/null) ||
    bf16_note="native_bf16 failed"
else
  device=cuda; seconds=${RUN_SECONDS:-40}; compile_seconds=${COMPILE_SECONDS:-40}; suffix=""
  runs=${runs:-"plain default"}
  if ! python -c "import sys, torch; sys.exit(not torch.cuda.is_available())" 2>/dev/null; then
    echo "gpu_check.sh: error: torch sees no CUDA device; on a CPU run" \
         "benchmarks/gpu_check.sh --quick" >&2
    exit 2
  fi
fi
out=${out:-runs/gpu_check-$(date -u +%Y%m%d-%H%M%S)$suffix}
if [ -e "$out" ]; then
  echo "gpu_check.sh: error: $out exists; give another --out" >&2
  exit 2
fi
mkdir -p "$out"
summary=$out/summary.md
failed=0
start=$SECONDS

{
  echo "# gpu_check.sh$([ $quick = 1 ] && echo " --quick") ($(date -u +%Y-%m-%dT%H:%M:%SZ))"
  echo
  echo "commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)" \
       "($(git status --porcelain 2>/dev/null | grep -vc '^??') tracked files changed)," \
       "host $(hostname), device $device:" \
       "$(python -c "import torch; print(torch.cuda.get_device_name() if torch.cuda.is_available()
                                       else 'no CUDA device')")," \
       "torch $(python -c "import torch; print(torch.__version__)")," \
       "python $(python -c "import platform; print(platform.python_version())")," \
       "MUJOCO_GL=$MUJOCO_GL; training modes: $runs" \
       "$([ -n "$skip" ] && echo "; skipped by request: $skip")"
} > "$summary"

wanted() { [[ " $skip " != *" $1 "* ]]; }
note() { printf '\n## %s\n' "$*" >> "$summary"; }

# step NAME LOG_LINES MIN_SECONDS COMMAND...: run it with its output in NAME.log, cut at what is
# left of the budget (the full form; --quick has none); skipped when less than MIN_SECONDS is left.
# The summary gets the command, status, seconds and the log's last LOG_LINES lines (0: none).
step() {
  local name=$1 lines=$2 least=$3
  shift 3
  local left=$((budget - (SECONDS - start)))
  if [ $quick = 0 ] && [ $left -lt "$least" ]; then
    note "$name: skipped, $left s of the ${budget} s budget left (it needs $least s)"
    return
  fi
  local began=$SECONDS limit=()
  [ $quick = 1 ] || limit=(timeout -k 10 "$left")
  "${limit[@]}" "$@" > "$out/$name.log" 2>&1
  local status=$?
  [ "$name" = "${name#train-}" ] || [ $status != 130 ] || status=0  # a run stopped by its timer
  [ $status = 0 ] || failed=1
  local said="FAILED (exit $status)"
  [ $status != 124 ] || said="CUT at the budget"
  [ $status != 0 ] || said=ok
  {
    echo
    echo "## $name: $said, $((SECONDS - began)) s"
    echo
    printf '   '; printf ' %q' "$@"; echo
    if [ "$lines" -gt 0 ]; then
      echo
      tail -n "$lines" "$out/$name.log"
    fi
  } >> "$summary"
}

# 1. Tests on the device.
if wanted tests; then
  slow_device_tests=()
  [ $quick = 1 ] && slow_device_tests=(-k "prefetcher or act_returns_bounded")
  step tests-device 1 30 env SEAR_TEST_DEVICE=$device python -m pytest -q -p no:cacheprovider \
    -m device "${slow_device_tests[@]}" tests/
  # Exact resume is a CPU property (CI runs it): CUDA's atomic adds make two runs of one seed
  # differ.
  cli_tests=(tests/test_cli.py
             -k "smoke_run_writes_csvs$([ $quick = 1 ] && echo " or resume_replays_exactly")")
  # --quick: CI has just run them in the full suite; here only that the selections still match.
  if [ $quick = 1 ]; then
    step tests-selections 1 0 env SEAR_TEST_DEVICE=$device python -m pytest -q -p no:cacheprovider \
      --collect-only -m device tests/
    step tests-cli 1 0 python -m pytest -q -p no:cacheprovider --collect-only "${cli_tests[@]}"
  else
    step tests-cli 1 30 python -m pytest -q -p no:cacheprovider "${cli_tests[@]}"
  fi
fi

# 2. What one update dispatches: ops, host syncs, host->device bytes (the GPU's own path on CUDA).
if wanted counts; then
  if [ $quick = 1 ]; then
    step counts 17 0 python benchmarks/update_counts.py --latent-dim 64 --hidden-dim 32 \
      --feature-dim 16 --batch-size 4 --top 0
  else
    step counts 17 20 python benchmarks/update_counts.py --device cuda --top 10
  fi
fi

# 3. The speed layer's table: the plain update and each device's gain over it, fp32 and TF32. The
# summary gets the table; the rest of the log (a compiler's warnings) stays in update.log.
if wanted update; then
  if [ $quick = 1 ]; then
    step update 0 0 python benchmarks/bench_speed.py --quick --methods drq sear
  else
    step update 0 90 python benchmarks/bench_speed.py --methods drq sear
  fi
  if [ -f "$out/update.log" ]; then
    echo >> "$summary"
    grep -E '^(## |\||Gain: |[0-9]+ alternating rounds|$)' "$out/update.log" | cat -s >> "$summary"
  fi
fi

# 4. Env steps/s, rendered through EGL (on the GPU when its driver provides EGL).
wanted envs && step envs 6 15 python benchmarks/bench_envs.py \
  --steps "$([ $quick = 1 ] && echo 3 || echo 300)" --envs cartpole-balance_sparse walker-walk

# 5. Training runs: the published-curve rung's command (EXPERIMENTS.md), sear, cut short by a timer.
rung=(--env cartpole-balance_sparse --method sear --seed 1 --action-repeat 2 --frame-stack 3
      --batch-size 256 --lr 1e-4 --nstep 3 --discount 0.99 --std-start 1.0 --std-end 0.1
      --std-steps 100000 --std-clip 0.3 --seed-frames 4000 --exploration-steps 2000 --update-every 2
      --critic-tau 0.01 --feature-dim 50 --hidden-dim 1024 --replay-size 100000
      --render-quality paper --frames 40000)
# One evaluation episode at frame 0 and none after: the timer is for training.
rung+=(--eval-episodes 1 --eval-every 1000000 --device $device)
[ $quick = 1 ] && rung+=(--frames 100 --seed-frames 80 --exploration-steps 40 --max-episode-steps 10
                         --batch-size 8 --latent-dim 64 --hidden-dim 32 --render-quality fast)
seed_frames=$([ $quick = 1 ] && echo 80 || echo 4000)
mode_flags() {
  case $1 in
    plain) echo --cuda-graph off --compile off --replay-device cpu --prefetch off ;;
    default) echo ;;
    graph) echo --compile off --cuda-graph on ;;
    compile) echo --compile on --cuda-graph off ;;
    tf32) echo --tf32 ;;
    bf16) echo --precision bf16 ;;
  esac
}
# Whether a mode's first update compiles: --compile on, or on CUDA left at auto.
compiles() {
  case $1 in
    compile) true ;;
    default|tf32|bf16) [ $device = cuda ] ;;
    *) false ;;
  esac
}
for mode in $runs; do
  wanted train || break
  if [[ $mode == graph || $mode == tf32 ]] && [ $device != cuda ]; then
    note "train-$mode: skipped, CUDA graphs and TF32 are CUDA's"
    continue
  fi
  if [ $mode = bf16 ] && [ -n "$bf16_note" ]; then
    note "train-$mode: skipped, this CPU emulates bf16 ($bf16_note)"
    continue
  fi
  s=$seconds
  compiles $mode && s=$((seconds + compile_seconds))
  least=$((s / 2 + 20))
  # its Ctrl-C timer ends inside the budget, with time to stop
  left=$((budget - (SECONDS - start) - 20))
  [ $quick = 1 ] || [ $left -ge $s ] || s=$left
  step "train-$mode" 0 $least timeout --preserve-status -s INT -k 15 "$s" \
    python sear.py "${rung[@]}" $(mode_flags $mode) --run-root "$out/train-$mode"
  [ -f "$out/train-$mode.log" ] || continue
  python - "$out/train-$mode.log" "$seed_frames" >> "$summary" <<'EOF'
import re, statistics, sys
# The progress lines (one per episode: its frames/s): a run stopped before its first snapshot
# removes its folder.
log, seed_frames = sys.argv[1], float(sys.argv[2])
eps = [(int(m[1]), float(m[2])) for m in
       re.finditer(r"^frame (\d+)/\d+ .*?\| ([\d.]+) fps \|.*? return ", open(log).read(), re.M)]
learning = [fps for frame, fps in eps if frame > seed_frames]
# the first learning episode holds any compiling
steady = learning[1:] if len(learning) > 1 else learning
last = f"frame {eps[-1][0]}" if eps else "no episode ended"
fps = statistics.median(steady) if steady else None
print(f"\n{last}; training after the seed frames: " + (
      f"first episode {learning[0]:.1f} frames/s, then median {fps:.1f} frames/s over "
      f"{len(steady)} episodes = {fps / 4:.2f} updates/s (action repeat 2, an update every 2 steps)"
      if len(learning) > 1 else
      f"{learning[0]:.1f} frames/s, one episode" if learning else "no episode ended"))
EOF
done

# 6. Where the plain update's time goes on the GPU: host time, kernels, copies, syncs
# (torch.profiler).
if wanted profile; then
  if [ $quick = 1 ]; then
    note "profile: skipped, it reads CUDA kernels and copies (tests/test_bench_agent.py checks" \
         "its summary on the CPU)"
  else
    step profile 40 30 python benchmarks/bench_agent.py --device cuda --profile --methods drq sear \
      --batch-size 256 --precisions fp32 --updates 10 --split-steps 0
  fi
fi

# 7. s/update and the share of the GEMM peaks measured in this run; a training step, part by part.
if wanted split; then
  if [ $quick = 1 ]; then
    step split 40 0 python benchmarks/bench_agent.py --device cpu --methods drq --batch-size 8 \
      --updates 1 --split-steps 2 --split-warmup 10 --split-method drq --env cartpole-balance_sparse
  else
    step split 40 30 python benchmarks/bench_agent.py --device cuda --updates 10 --split-steps 100 \
      --split-warmup 300 --env cartpole-balance_sparse
  fi
fi

# 8. channels_last against NCHW.
if wanted layouts; then
  if [ $quick = 1 ]; then
    step layouts 6 0 python benchmarks/bench_agent.py --device cpu --compare-layouts --methods drq \
      --precisions fp32 --batch-size 8 --rounds 1 --updates 1
  else
    step layouts 6 20 python benchmarks/bench_agent.py --device cuda --compare-layouts --rounds 3 \
      --updates 10
  fi
fi

total=$((SECONDS - start))
{
  echo
  echo "## total: $total s$([ $quick = 0 ] &&
       echo ", budget $budget s: $([ $total -le $budget ] && echo within || echo OVER)")," \
       "$([ $failed = 0 ] && echo "every step that ran passed" || echo "SOME STEPS FAILED")"
} >> "$summary"
cat "$summary"
exit $failed
