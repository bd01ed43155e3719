#!/usr/bin/env bash
# A GPU machine to figures in one run (issue 35; `make gpu-check` calls it with the .venv's
# python). Every step runs under its own time limit and the run's deadline; one that fails is
# recorded and the next runs. Logs and figures go to $WORK and are packed after every step into
# $DEST (what a lent GPU machine sends back: at most 8 files, so one .tgz beside the summary).
#
#   PYTHON        the interpreter (default: python3, the machine's own torch, never reinstalled)
#   GPU_STEPS     comma list of steps (default: all, in this order):
#                 env install gsplat tests holo train pipeline frame refine net build
#   GPU_DEADLINE_S  seconds the whole run may take (default 560); each step gets what is left
#   GPU_VIEWS     views per measured configuration (default 30)
#   OUT           where the packed results go (default out/gpu)
#   GPU_BUILD_STEPS  build: train the default recipe for this many steps instead of its own
#
# install: the wheels in .whl/ (the packages the machine lacks, `pip install --no-deps`) and
# nhfd itself (editable, no build isolation: nothing is downloaded). gsplat: the CUDA extension
# built ahead for sm_90 against torch 2.11.0+cu130 (.gpu/, docs/gpu.md says how) is tried
# first; if it does not load, gsplat compiles its own for this GPU (timed, MAX_JOBS = cores).
set -u
REPO=$(cd "$(dirname "$0")/.." && pwd)
cd "$REPO"
PY=${PYTHON:-python3}
DEST=${OUT:-$REPO/out/gpu}
WORK=${GPU_WORK:-/tmp/nhfd-gpu}
STEPS=${GPU_STEPS:-env,install,gsplat,tests,holo,train,pipeline,frame,refine,net,build}
DEADLINE=$(( $(date +%s) + ${GPU_DEADLINE_S:-560} ))
VIEWS=${GPU_VIEWS:-30}
# The CUDA tests: every test that needs CUDA, and the ones that check their CPU halves.
GPU_TESTS="tests/pipeline/test_device.py tests/scene/test_gsplat_conventions.py
  tests/models/test_fp16.py tests/models/test_amp.py tests/dataset/test_build_device.py
  tests/models/test_torch_model.py
  tests/pipeline/test_refine.py::test_refine_on_the_gpu_follows_the_cpu
  tests/models/test_eval_stacks.py::test_evaluation_on_the_gpu_scores_as_on_the_cpu
  tests/models/test_train.py::test_a_cuda_run_resumes_on_the_cpu_from_the_same_step
  tests/test_require_cuda.py"
export NHFD_SHARED_DATA=${NHFD_SHARED_DATA:-$REPO/.gpu/shared/data}
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg
mkdir -p "$DEST" "$WORK"
: > "$WORK/steps.log"

pack() {
  tar -czf "$DEST/gpu_check.tgz.part" -C "$WORK" --exclude='./ds' --exclude='./run' \
    --exclude='./build' . 2>/dev/null && mv "$DEST/gpu_check.tgz.part" "$DEST/gpu_check.tgz"
  cp "$WORK/steps.log" "$DEST/steps.log"
}

# step NAME LIMIT_S COMMAND...: run COMMAND (a function below) when NAME is in GPU_STEPS, under
# min(LIMIT_S, what the deadline leaves), its output in $WORK/NAME.log.
step() {
  local name=$1 limit=$2 left rc start
  shift 2
  case ",$STEPS," in *",$name,"*) ;; *) return 0 ;; esac
  left=$(( DEADLINE - $(date +%s) - 5 ))
  if [ "$left" -lt 20 ]; then
    echo "$name: skipped, ${left}s left before the deadline" | tee -a "$WORK/steps.log"
    return 0
  fi
  [ "$limit" -gt "$left" ] && limit=$left
  start=$(date +%s)
  echo "=== $name (limit ${limit}s)" | tee -a "$WORK/steps.log"
  timeout -k 5 "$limit" bash -c "$*" > "$WORK/$name.log" 2>&1
  rc=$?
  echo "$name: rc=$rc in $(( $(date +%s) - start ))s" | tee -a "$WORK/steps.log"
  tail -n 15 "$WORK/$name.log"
  pack
}

nhfd() { "$PY" -m nhfd.cli.main "$@"; }

do_env() {
  nvidia-smi || true
  "$PY" -c "import torch; print(torch.__version__, torch.cuda.is_available())"
}

do_install() {
  local site
  site=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
  [ -w "$site" ] || { echo "$site is not writable: run with a python whose packages can change"; return 1; }
  if compgen -G ".whl/*.whl" > /dev/null; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade .whl/*.whl || return 1
  fi
  "$PY" -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir -e . || return 1
  "$PY" scripts/gpu_probe.py env --json "$WORK/env.json"
}

do_gsplat() {
  local gdir suffix so cc t0
  gdir=$("$PY" -c "import importlib.util as u; print(u.find_spec('gsplat').submodule_search_locations[0])")
  suffix=$("$PY" -c "import sysconfig; print(sysconfig.get_config_var('EXT_SUFFIX'))")
  so=.gpu/gsplat_csrc$suffix
  if [ -f "$so" ]; then
    cp "$so" "$gdir/csrc$suffix"
    "$PY" scripts/gpu_probe.py gsplat --json "$WORK/gsplat.json" && return 0
    echo "the carried extension did not load or render: compiling gsplat's own"
    rm -f "$gdir/csrc$suffix"
  fi
  cc=$("$PY" -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
  t0=$(date +%s)
  MAX_JOBS=$(nproc) TORCH_CUDA_ARCH_LIST=$cc "$PY" scripts/gpu_probe.py gsplat --json "$WORK/gsplat.json" || return 1
  echo "gsplat JIT build for sm_${cc/./} with MAX_JOBS=$(nproc): $(( $(date +%s) - t0 ))s"
}

do_tests() {
  # shellcheck disable=SC2086
  NHFD_REQUIRE_CUDA=1 "$PY" -m pytest -q -rfEs -p no:cacheprovider --durations=15 -o junit_family=xunit1 \
    --junitxml="$WORK/junit.xml" $GPU_TESTS
}

do_pipeline() {
  # The GPU with and without CUDA graphs side by side (the same views in turns), then the CPU
  # path on the same machine (fewer views: 0.2 to 0.5 s each).
  nhfd bench pipeline --device cuda --cuda-graphs on,off --frame-size-px 1024 576 \
    --frame-size-px 1920 1080 --views "$VIEWS" --json "$WORK/gpu_pipeline.json" || return 1
  nhfd bench pipeline --device cpu --frame-size-px 1024 576 --frame-size-px 1920 1080 \
    --views 10 --json "$WORK/cpu_pipeline.json"
}

do_net() { "$PY" scripts/gpu_probe.py net --views 50 --json "$WORK/net.json"; }

do_frame() { "$PY" scripts/gpu_probe.py frame --views "$VIEWS" --json "$WORK/frame.json"; }

# Issue 34's GPU figure: ms per sgd iteration at 1920 x 1080, the CPU beside it in the same run.
do_refine() { nhfd bench refine --devices cpu,cuda --iterations 8 --out "$WORK/refine.json"; }

do_holo() {
  nhfd bench holo --device cuda --scene models/scenes/donut.ply --out "$WORK/holo_cuda.json" &&
    nhfd bench holo --device cpu --scene models/scenes/donut.ply --sizes 1024x576 \
      --out "$WORK/holo_cpu.json"
}

do_train() {
  nhfd dataset build --device cuda --scene models/scenes/donut.ply --views 24 --size 512x288 \
    --out "$WORK/ds" || return 1
  nhfd train --device cuda --data "$WORK/ds" --out "$WORK/run" --steps 200 --no-progress || return 1
  cp "$WORK/run/train_log.csv" "$WORK/run/run.json" "$WORK/" 2>/dev/null
  "$PY" scripts/gpu_probe.py train "$WORK/run" --json "$WORK/train.json" || return 1
  # Where a training step's time goes (host parts, device busy time, top kernels).
  "$PY" scripts/gpu_probe.py trainprof "$WORK/ds" --views 110 --json "$WORK/trainprof.json"
}

do_build() {
  # GPU_BUILD_STEPS (when set): the default recipe with fewer training steps, to fit a short
  # lease; report.json's seconds per step gives the full recipe's training time.
  local cfg=()
  if [ -n "${GPU_BUILD_STEPS:-}" ]; then
    printf '[model.build.profiles.default]\nsteps = %d\n' "$GPU_BUILD_STEPS" > "$WORK/build.toml"
    cfg=(--config "$WORK/build.toml")
  fi
  nhfd model build models/scenes/donut.ply --device cuda --out "$WORK/build" --no-progress \
    "${cfg[@]}"
  local rc=$?
  cp "$WORK/build/report.json" "$WORK/build_report.json" 2>/dev/null
  return $rc
}

# `timeout` runs a new bash: it needs the functions and settings exported.
export -f nhfd do_env do_install do_gsplat do_tests do_pipeline do_net do_frame do_refine do_holo do_train \
  do_build
export PY WORK VIEWS GPU_TESTS GPU_BUILD_STEPS
step env 30 do_env
step install 120 do_install
step gsplat 300 do_gsplat
step tests 300 do_tests
step holo 240 do_holo
step train 240 do_train
step pipeline 240 do_pipeline
step frame 120 do_frame
step refine 150 do_refine
step net 120 do_net
step build 600 do_build
pack
if grep -h "rc=" "$WORK/steps.log" | grep -v "rc=0 "; then
  echo "gpu-check: the steps above failed; logs and figures in $DEST/gpu_check.tgz"
  exit 1
fi
echo "gpu-check: every step passed; logs and figures in $DEST/gpu_check.tgz"
