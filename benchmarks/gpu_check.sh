#!/usr/bin/env bash
# What only a GPU can show, in <= 8 minutes on one GPU, into one summary file:
#   1. the tests that take a device (tests/conftest.py: SEAR_TEST_DEVICE=cuda, `-m device`), and sear.py's
#      smoke run and exact --resume test (test_cli.py; sear.py picks CUDA itself with --device auto)
#   2. three training runs of the published-curve rung's command (cartpole-balance_sparse, sear, DrQ-v2's
#      config, EXPERIMENTS.md), RUN_SECONDS each (default 90: with 3 x 120 s the rest would not fit in
#      8 minutes): --prefetch off, --prefetch on, and --prefetch on in bf16; stopped by Ctrl-C (SIGINT)
#   3. bench_agent.py on CUDA: s/update and the share of the GPU's fp32 / bf16 GEMM peak measured in the
#      same run, and a training step split into env / act / sample / update
#   4. bench_envs.py: env steps/s with MUJOCO_GL=egl, and which OpenGL renderer drew them (the GPU's,
#      or Mesa's llvmpipe if EGL fell back to software)
#
#   benchmarks/gpu_check.sh [--out DIR]    on a machine with a CUDA GPU
#   benchmarks/gpu_check.sh --quick        the same steps on the CPU with tiny budgets (CI, so this cannot rot)
#
# --quick runs a fast subset of the device tests and only collects the rest (a test selection that no
# longer matches anything fails), trains tiny networks for a few hundred frames, and benchmarks at batch 8.
# Writes DIR (default runs/gpu_check-<UTC time>[-quick]; never an existing one): summary.md, each step's
# log, the training runs. Exit status: 0 when every step passed, 1 otherwise, 2 for bad arguments.
set -uo pipefail
cd "$(dirname "$0")/.."
quick=0
out=""
while [ $# -gt 0 ]; do
  case $1 in
    --quick) quick=1 ;;
    --out) [ $# -ge 2 ] || { echo "gpu_check.sh: error: --out needs a directory" >&2; exit 2; }; out=$2; shift ;;
    *) echo "gpu_check.sh: error: unknown argument $1 (use --quick, --out DIR)" >&2; exit 2 ;;
  esac
  shift
done
export MUJOCO_GL=${MUJOCO_GL:-egl}
if [ $quick = 1 ]; then
  device=cpu; seconds=${RUN_SECONDS:-60}; suffix=-quick
else
  device=cuda; seconds=${RUN_SECONDS:-90}; suffix=""
  if ! python -c "import sys, torch; sys.exit(not torch.cuda.is_available())" 2>/dev/null; then
    echo "gpu_check.sh: error: torch sees no CUDA device; on a CPU run benchmarks/gpu_check.sh --quick" >&2
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
  echo "commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown), host $(hostname), device $device:" \
       "$(python -c "import torch; print(torch.cuda.get_device_name() if torch.cuda.is_available() else 'no CUDA device')")," \
       "torch $(python -c "import torch; print(torch.__version__)"), MUJOCO_GL=$MUJOCO_GL"
} > "$summary"

# step NAME LOG_LINES COMMAND...: run it with its output in NAME.log; the summary gets the command,
# status, seconds and the log's last LOG_LINES lines (0: none).
step() {
  local name=$1 lines=$2
  shift 2
  local began=$SECONDS
  "$@" > "$out/$name.log" 2>&1
  local status=$?
  [ "$name" = "${name#train-}" ] || [ $status != 130 ] || status=0  # a training run stopped by its timer
  [ $status = 0 ] || failed=1
  {
    echo
    echo "## $name: $([ $status = 0 ] && echo ok || echo "FAILED (exit $status)"), $((SECONDS - began)) s"
    echo
    printf '   '; printf ' %q' "$@"; echo
    if [ "$lines" -gt 0 ]; then
      echo
      tail -n "$lines" "$out/$name.log"
    fi
  } >> "$summary"
}

# 1. Tests on the device.
slow_device_tests=()
[ $quick = 1 ] && slow_device_tests=(-k "prefetcher or act_returns_bounded")
step tests-device 1 env SEAR_TEST_DEVICE=$device python -m pytest -q -p no:cacheprovider -m device \
  "${slow_device_tests[@]}" tests/
cli_tests=(tests/test_cli.py -k "smoke_run_writes_csvs or resume_replays_exactly")
if [ $quick = 1 ]; then  # CI has just run them in the full suite: here only that the selections still match
  step tests-selections 1 env SEAR_TEST_DEVICE=$device python -m pytest -q -p no:cacheprovider --collect-only \
    -m device tests/
  step tests-cli 1 python -m pytest -q -p no:cacheprovider --collect-only "${cli_tests[@]}"
else
  step tests-cli 1 python -m pytest -q -p no:cacheprovider "${cli_tests[@]}"
fi

# 2. Training runs: the published-curve rung's command (EXPERIMENTS.md), sear, cut short by a timer.
rung=(--env cartpole-balance_sparse --method sear --seed 1 --action-repeat 2 --frame-stack 3 --batch-size 256
      --lr 1e-4 --nstep 3 --discount 0.99 --std-start 1.0 --std-end 0.1 --std-steps 100000 --std-clip 0.3
      --seed-frames 4000 --exploration-steps 2000 --update-every 2 --critic-tau 0.01 --feature-dim 50
      --hidden-dim 1024 --replay-size 100000 --render-quality paper --frames 40000)
# One evaluation episode at frame 0 and none after: the timer is for training.
rung+=(--eval-episodes 1 --eval-every 1000000 --device $device)
[ $quick = 1 ] && rung+=(--frames 100 --seed-frames 80 --exploration-steps 40 --max-episode-steps 10
                         --batch-size 8 --latent-dim 64 --hidden-dim 32 --render-quality fast)
seed_frames=$([ $quick = 1 ] && echo 80 || echo 4000)
for variant in "prefetch-off fp32 off" "prefetch-on fp32 on" "prefetch-on-bf16 bf16 on"; do
  set -- $variant
  step "train-$1" 0 timeout --preserve-status -s INT -k 60 "$seconds" python sear.py "${rung[@]}" --precision "$2" \
    --prefetch "$3" --run-root "$out/train-$1"
  python - "$out/train-$1" "$seed_frames" >> "$summary" <<'EOF'
import csv, glob, statistics, sys
root, seed_frames = sys.argv[1], float(sys.argv[2])
paths = glob.glob(f"{root}/*/train.csv")
rows = list(csv.DictReader(open(paths[0]))) if paths else []
learning = [float(r["fps"]) for r in rows if float(r["frame"]) > seed_frames and r["critic_loss"] != ""]
last = f"frame {rows[-1]['frame']} after {float(rows[-1]['wall_time']):.0f} s" if rows else "no episode ended"
fps = statistics.median(learning) if learning else None
print(f"\n{last}; training after the seed frames, median of {len(learning)} episodes: "
      + (f"{fps:.1f} frames/s = {fps / 4:.2f} updates/s (action repeat 2, an update every 2 steps)" if fps
         else "no episode ended"))
EOF
done

# 3. The update on the device: s/update, share of the GEMM peaks measured in this run, the step split.
if [ $quick = 1 ]; then
  step bench-agent 40 python benchmarks/bench_agent.py --device cpu --methods drq --batch-size 8 --updates 1 \
    --split-steps 2 --split-warmup 10 --split-method drq --env cartpole-balance_sparse
else
  step bench-agent 40 python benchmarks/bench_agent.py --device cuda --updates 20 --split-steps 200 \
    --env cartpole-balance_sparse
fi

# 4. Env steps/s, rendered through EGL (on the GPU when its driver provides EGL).
step bench-envs 6 python benchmarks/bench_envs.py --steps "$([ $quick = 1 ] && echo 3 || echo 300)" \
  --envs cartpole-balance_sparse walker-walk

total=$((SECONDS - start))
{
  echo
  echo "## total: $total s$([ $quick = 0 ] && echo ", budget 480 s: $([ $total -le 480 ] && echo within || echo OVER)")," \
       "$([ $failed = 0 ] && echo "every step passed" || echo "SOME STEPS FAILED")"
} >> "$summary"
cat "$summary"
exit $failed
