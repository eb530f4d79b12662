#!/usr/bin/env bash
# The release suite on a GPU machine, from the repository root, into $OUT (default benchmarks/results/<GPU kind>):
#
#   bash benchmarks/gpu/release.sh [STAGE...] [-- ARGS...]
#
# STAGE, in this order by default: tests integration e1 e2 e3 e4 e5 floor report (the others on request).
#   tests        every gpu-marked test: tests1, tests2 and tests3    env.txt, gpu_tests.log
#   tests1       ... the compile backend's and cameras' tests, NMS and the detector's eager static path
#   tests2       ... the detector compiled, device mailboxes, the engine on the GPU (but bench cameras)
#   tests3       ... every other gpu test (a new test file lands here)
#   integration  the core integration tests on CUDA                  integration_tests_on_cuda.log
#   e1           E1 at 8 heads                                       paper_cuda_e1.json
#   e2           E2 at 1, 2, 4, 8 detection heads, with MPS          paper_cuda_e2.json
#   e3           E3, MPS off vs on                                   paper_cuda_e3.json
#   e4           E4, rate limits                                     paper_cuda_e4.json
#   e5           E5, 10,000 frames at 30 Hz (E5_FRAMES)              paper_cuda_e5.json
#   floor        the floor of depth + seg and of depth + seg + det   paper_cuda_floor_depth_seg{,_det}.json
#   resources    device memory per extra head, CPU idle and at 30 Hz resources_gpu.json
#   hop          one mailbox hop of ViT-S features in device memory   hop_cuda_vits-1080p.json
#   boundary     E5 with 1080p frames into a 1280x720 canvas (E5_FRAMES)  paper_cuda_e5_boundary.json
#   cameras      4 cameras at 30 Hz; 1, 2, 4, 8 cameras batched vs apart  cameras_cuda.json
#   web          E5's heads at 30 Hz with the live view open and not   web_overhead_cuda.json
#   street       the README's GPU command on the street video, with its rate limits and without
#                                                                     run_street_{limits,unlimited}.json
#   report       vpengine bench report on $OUT                       summary.md, summary.png
# ARGS go to every `vpengine bench paper` after the stage's own, so they win (e.g. -- --set mode=thread, or
# -- --heads 8 for a shorter E2); CONFIG is its config (configs/bench.yaml).
# Each stage ends within its time limit (T_<STAGE> seconds, defaults below), so stages can be grouped into calls of
# at most 10 minutes: tests1; tests2; tests3; integration; e1; floor; e2; e3 e4; e5. With an empty compile cache the
# gpu tests take about 15 minutes (most of it compiling), hence three parts; with a warm one `tests` fits one call.
# PYTEST_ARGS go to every pytest run (e.g. -x, or --collect-only to list what a part selects). Every benchmark's
# output is in release.log.
source benchmarks/gpu/setup.sh
set -o pipefail
CONFIG=${CONFIG:-configs/bench.yaml}

stages=() args=()
while [ $# -gt 0 ]; do
  if [ "$1" = "--" ]; then shift; args=("$@"); break; fi
  stages+=("$1"); shift
done
[ ${#stages[@]} -gt 0 ] || stages=(tests integration e1 e2 e3 e4 e5 floor report)

# paper SECONDS TAG ARGS...: `vpengine bench paper` into $OUT, its result lines on the console
paper() {
  local t=$1 tag=$2; shift 2
  timeout "$t" "$PYTHON" -m vpengine.cli.main bench paper --config "$CONFIG" --tag "$tag" --out "$OUT" "$@" \
    "${args[@]}" 2>&1 | tee -a "$OUT/release.log" | grep "E[1-5] \|floor\|MPS daemon\|Error\|error\|->"
}

# the gpu tests in parts, each within a call on an empty compile cache (tests1 starts gpu_tests.log, the others add)
G=tests/gpu DET=tests/gpu/test_detection_cuda.py
PART1=($G/test_cameras_cuda.py $G/test_compile_cuda.py "$DET::test_triton_nms_keeps_what_batched_nms_keeps_on_the_cpu"
  "$DET::test_static_path_on_cuda_equals_torchvision_and_never_syncs")
PART2=("$DET::test_compiled_static_path_is_one_cuda_graph_per_batch_size_and_equals_torchvision"
  "$DET::test_lite_recipe_at_1080p_compiled_is_faster_than_torchvision_eager" $G/test_device_rings_cuda.py
  $G/test_engine_gpu.py -k "not bench_cameras")
PART3=("$G/test_engine_gpu.py::test_bench_cameras_in_thread_mode_runs_its_engines_one_after_another_in_one_process")
for f in $G/test_*.py; do  # every file the first two parts do not run: a new one lands here
  case $f in */test_cameras_cuda.py | */test_compile_cuda.py | "$DET" | */test_device_rings_cuda.py) ;;
    */test_engine_gpu.py) ;;
    *) PART3+=("$f") ;;
  esac
done
# gpu_tests PART...: each part's tests (PART1, PART2, PART3), its lines into gpu_tests.log
gpu_tests() {
  local part sel
  if [ "$1" = 1 ]; then
    {
      nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
      "$PYTHON" -c "import sys, torch; print(sys.version); print('torch', torch.__version__, 'cuda', torch.version.cuda)"
      which nvidia-cuda-mps-control
    } 2>&1 | tee "$OUT/env.txt"
    : > "$OUT/gpu_tests.log"
  fi
  for part in "$@"; do
    sel="PART$part[@]"
    echo "== gpu tests, part $part, $(date -u +%FT%TZ)" >> "$OUT/gpu_tests.log"
    # shellcheck disable=SC2086
    timeout "${T_TESTS:-560}" "$PYTHON" -m pytest -m gpu -v -p no:cacheprovider ${PYTEST_ARGS:-} "${!sel}" 2>&1 \
      | tee -a "$OUT/gpu_tests.log" | tail -5
  done
}

for stage in "${stages[@]}"; do
  echo "== $stage"
  case $stage in
    tests) gpu_tests 1 2 3 ;;
    tests[123]) gpu_tests "${stage#tests}" ;;
    integration)
      # the DINOv2 engine tests read a 1080p frame from ../shared/data/media, which the GPU machine lacks: carry it
      # in .media/ (cp ../shared/data/media/cheetah_1080p_0.jpg .media/)
      if [ -d .media ]; then mkdir -p ../shared/data/media && cp .media/* ../shared/data/media/; fi
      VPENGINE_TEST_DEVICE=cuda timeout "${T_INTEGRATION:-560}" "$PYTHON" -m pytest -q -p no:cacheprovider \
        tests/integration/test_pipeline.py tests/integration/test_ring_processes.py tests/integration/test_faults.py \
        tests/integration/test_rates.py tests/integration/test_idle.py tests/integration/test_input_modes.py \
        tests/integration/test_dinov2_engine.py 2>&1 | tee "$OUT/integration_tests_on_cuda.log" | tail -15 ;;
    e1) paper "${T_E1:-300}" e1 --experiments E1 --heads 8 ;;
    e2) paper "${T_E2:-540}" e2 --experiments E2 --heads 1,2,4,8 --frames 50 --set mps=required ;;
    e3) paper "${T_E3:-400}" e3 --experiments E3 --frames 50 ;;
    e4) paper "${T_E4:-120}" e4 --experiments E4 ;;
    e5) paper "${T_E5:-560}" e5 --experiments E5 --e5-frames "${E5_FRAMES:-10000}" ;;
    floor)
      paper "${T_FLOOR:-200}" floor_depth_seg --experiments floor --floor-heads depth,seg --frames 200 --results borrow
      paper "${T_FLOOR:-200}" floor_depth_seg_det --experiments floor --floor-heads depth,seg,det --frames 200 \
        --results borrow ;;
    resources)
      timeout "${T_RESOURCES:-400}" "$PYTHON" -m vpengine.cli.main bench resources --config "$CONFIG" --heads 1,2,4 \
        --out "$OUT" 2>&1 | tee -a "$OUT/release.log" | tail -4 ;;
    hop)
      timeout "${T_HOP:-120}" "$PYTHON" -m vpengine.cli.main bench hop --device cuda --layout vits-1080p --out "$OUT" \
        2>&1 | tee -a "$OUT/release.log" | tail -2 ;;
    boundary) paper "${T_BOUNDARY:-560}" e5_boundary --experiments E5 --e5-frames "${E5_FRAMES:-10000}" \
      --set input.height=720 --set input.width=1280 --frame-size 1920x1080 ;;
    cameras)
      timeout "${T_CAMERAS:-560}" "$PYTHON" -m vpengine.cli.main bench cameras --cameras "${CAMERA_COUNTS:-1,2,4,8}" \
        --out "$OUT" --name cameras_cuda 2>&1 | tee -a "$OUT/release.log" | grep "stream\|throughput\|rror\|json" ;;
    web)
      timeout "${T_WEB:-300}" "$PYTHON" -m vpengine.cli.main bench web -c configs/dinov2s_depth_seg_det.yaml \
        --random-weights --device cuda --set heads.seg.rate_hz=null --set heads.det.rate_hz=null --seconds 15 \
        --rounds 2 --out "$OUT" --name web_overhead_cuda 2>&1 | tee -a "$OUT/release.log" | tail -4 ;;
    street)
      # the street video from ../shared/data/media, carried in .media/ (cp ../shared/data/media/vtest.avi .media/)
      video=.media/vtest.avi
      [ -f "$video" ] || video=sample:street
      for variant in limits unlimited; do
        extra=()
        [ $variant = limits ] || extra=(--set heads.seg.rate_hz=null --set heads.det.rate_hz=null)
        rm -rf "/tmp/street_$variant"
        timeout "${T_STREET:-200}" "$PYTHON" -m vpengine.cli.main run -c dinov2s_depth_seg_det -s "$video" \
          --random-weights --out "/tmp/street_$variant" --save-every 100000 "${extra[@]}" 2>&1 \
          | tee -a "$OUT/release.log" | tail -7
        cp "/tmp/street_$variant/summary.json" "$OUT/run_street_$variant.json"
      done ;;
    report) vpengine bench report --results "$OUT" --out "$OUT" ;;
    *) echo "unknown stage $stage; accepted: tests tests1 tests2 tests3 integration e1 e2 e3 e4 e5 floor resources" \
      "hop boundary cameras web street report"; exit 2 ;;
  esac
done
