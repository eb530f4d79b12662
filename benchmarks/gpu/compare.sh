#!/usr/bin/env bash
# Before/after: `vpengine bench paper` of two trees on one machine in one call, each experiment run for the
# older tree and then for this one, then the report of each run against the older one's. From the repository root:
#
#   bash benchmarks/gpu/compare.sh BEFORE [EXPERIMENT...]
#
# BEFORE: a folder holding the older tree's src/ (and configs/), or a commit of this repository, checked out with
# git worktree under /tmp. Where the machine has no .git, make the folder where the repository is and carry it along
# (git ignores .before/): mkdir .before && git archive COMMIT src configs | tar -x -C .before
# AFTER: the newer tree (default: this one). EXPERIMENT: E1, floor, E5, cameras (default: the first three; E1 is the
# engine against independent models at HEADS=8 heads, the floor of FLOOR_HEADS=depth,seg, E5 a stream of
# E5_FRAMES=3000 frames, cameras `vpengine bench cameras` with CAMERAS=4 cameras: their 30 Hz stream and one engine
# batched against one a camera).
# Also FRAMES (100 lockstep frames), RESULTS (borrow: the caller borrows results, so the numbers are the engine's
# rather than its copies), MODE (the config's, process), ROUNDS (1: before, after; 2: before, after, before, after),
# T (each run's time limit, 290 s), CONFIG (configs/bench.yaml; configs/tiny.yaml runs tiny models on the CPU),
# SETS (space-separated KEY=VALUE overrides given to both trees, e.g. SETS=heads.det.backend=eager to run the same
# backends where the trees' configs differ).
# Writes paper_<device>_{before,after}_<experiment>[_<round>].json (cameras_{before,after}[_<round>].json), summary.md and summary.png into $OUT, by default
# benchmarks/results/<GPU kind>/before_after/; "change" in summary.md is each after-run's number against the
# before-run's (+: slower).
given=${OUT:-}
source benchmarks/gpu/setup.sh
[ -n "$given" ] || { OUT=$OUT/before_after; mkdir -p "$OUT"; }
set -o pipefail
[ $# -ge 1 ] || { echo "usage: bash benchmarks/gpu/compare.sh BEFORE [EXPERIMENT...]"; exit 2; }
BEFORE=$1; shift
experiments=("$@")
[ ${#experiments[@]} -gt 0 ] || experiments=(E1 floor E5)
CONFIG=${CONFIG:-configs/bench.yaml}

# tree DIR-OR-COMMIT: the folder of that tree
tree() {
  if [ -d "$1/src/vpengine" ]; then (cd "$1" && pwd); return; fi
  local dir=/tmp/vpengine-$1
  if [ ! -d "$dir" ]; then
    git worktree add --detach "$dir" "$1" >&2 || {
      echo "$1 is neither a folder with src/vpengine nor a commit git can check out here; make the folder where" \
        "the repository is: mkdir .before && git archive COMMIT src configs | tar -x -C .before" >&2
      return 1
    }
  fi
  echo "$dir"
}
before=$(tree "$BEFORE") || exit 1
after=$(tree "${AFTER:-.}") || exit 1
echo "before: $BEFORE ($before), after: ${AFTER:-this tree} ($after), on $OUT"

# run SIDE TREE EXPERIMENT TAG: one `vpengine bench paper` (or `bench cameras`) of that tree, in the dialect of its CLI
run() {
  local side=$1 tree=$2 exp=$3 tag=$4
  local path="$SITE$tree/src"
  local sets=()
  for kv in ${SETS:-}; do sets+=(--set "$kv"); done
  if [ "$exp" = cameras ]; then
    echo "-- $side $exp"
    PYTHONPATH=$path TORCHINDUCTOR_CACHE_DIR=/tmp/inductor-$side TRITON_CACHE_DIR=/tmp/triton-$side \
      timeout "${T:-290}" "$PYTHON" -m vpengine.cli.main bench cameras --config "$tree/$CONFIG" \
      --stream-cameras "${CAMERAS:-4}" --cameras "${CAMERAS:-4}" --name "cameras_${tag/_cameras/}" --out "$OUT" \
      "${sets[@]}" 2>&1 \
      | grep "stream:\|throughput,\|Error\|error"
    return
  fi
  local args=(--experiments "$exp" --heads "${HEADS:-8}" --frames "${FRAMES:-100}" --e5-frames "${E5_FRAMES:-3000}"
    --floor-heads "${FLOOR_HEADS:-depth,seg}" --results "${RESULTS:-borrow}" --tag "$tag" --out "$OUT")
  if PYTHONPATH=$path "$PYTHON" -m vpengine.cli.main bench paper --help | grep -q -- "--set KEY=VALUE"; then
    args+=(--config "$tree/$CONFIG" "${sets[@]}")  # this release's CLI: the engine is the config's
    [ -z "${MODE:-}" ] || args+=(--set "mode=$MODE")
  else  # the CLI before it: the same models by flags
    case $CONFIG in
      *tiny.yaml) args+=(--tiny --device cpu) ;;
      *) args+=(--backend compile --det-head frcnn_dinov2_lite) ;;
    esac
    [ -z "${MODE:-}" ] || args+=(--mode "$MODE")
  fi
  echo "-- $side $exp"
  # each tree compiles into its own caches: a kernel or graph cached by the other tree must never be reused
  PYTHONPATH=$path TORCHINDUCTOR_CACHE_DIR=/tmp/inductor-$side TRITON_CACHE_DIR=/tmp/triton-$side \
    timeout "${T:-290}" "$PYTHON" -m vpengine.cli.main bench paper "${args[@]}" 2>&1 \
    | grep "E1 N=\|E5 [0-9]* frames at\|floor\|Error\|error"
}

for exp in "${experiments[@]}"; do
  for ((round = 1; round <= ${ROUNDS:-1}; round++)); do
    suffix=$([ "$round" = 1 ] || echo "_$round")
    run before "$before" "$exp" "before_${exp,,}$suffix"
    rm -f "$OUT"/paper_*_before_*.png  # the older CLI draws a figure per run; the report draws them all
    run after "$after" "$exp" "after_${exp,,}$suffix"
  done
done
vpengine bench report --results "$OUT" --out "$OUT" --baseline before
