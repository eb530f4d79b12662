#!/usr/bin/env bash
# The release suite on a GPU machine, from the repository root, into $OUT (default benchmarks/results/<GPU kind>):
#
#   bash benchmarks/gpu/release.sh [STAGE...] [-- ARGS...]
#
# STAGE, in this order by default: tests integration e1 e2 e3 e4 e5 floor report (the others on request).
#   tests        every gpu-marked test                               env.txt, gpu_tests.log
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
# at most 10 minutes: tests; integration; e1; floor; e2; e3 e4; e5. Every benchmark's output is in release.log.
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

for stage in "${stages[@]}"; do
  echo "== $stage"
  case $stage in
    tests)
      {
        nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
        "$PYTHON" -c "import sys, torch; print(sys.version); print('torch', torch.__version__, 'cuda', torch.version.cuda)"
        which nvidia-cuda-mps-control
      } 2>&1 | tee "$OUT/env.txt"
      timeout "${T_TESTS:-560}" "$PYTHON" -m pytest -m gpu tests/gpu -q -p no:cacheprovider 2>&1 \
        | tee "$OUT/gpu_tests.log" | tail -15 ;;
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
      # Faster R-CNN compiled without CUDA graphs (its NMS syncs with the host): 4 cameras at 30 Hz need it
      timeout "${T_CAMERAS:-560}" "$PYTHON" -m vpengine.cli.main bench cameras --cameras "${CAMERA_COUNTS:-1,2,4,8}" \
        --set heads.det.backend=compile --set 'heads.det.backend_options={cudagraphs: false, fullgraph: false}' \
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
    *) echo "unknown stage $stage; accepted: tests integration e1 e2 e3 e4 e5 floor resources hop boundary cameras" \
      "web street report"; exit 2 ;;
  esac
done
