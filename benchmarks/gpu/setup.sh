# Sourced at the start of every GPU-machine command (see /work/.library/device/README.md):
# installs the carried cp312 wheels (pydantic) and puts the source tree on the path.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  || { echo "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD/src:$PWD/tests
export PYTHONUNBUFFERED=1
mkdir -p "${OUT:-/tmp/out}"
# floor SECONDS HEADS TAG ARGS...: the floor experiment (compiled, borrowed results, 200 frames) into $OUT, printing its
# result line
floor() {
  local t=$1 heads=$2 tag=$3; shift 3
  timeout "$t" python3 -m vpengine.cli.main bench paper --experiments floor --floor-heads "$heads" --backend compile \
    --frames 200 --results borrow --tag "$tag" --out "$OUT" "$@" 2>&1 | grep "floor:\|Error" | tail -2
}
# paper SECONDS ARGS...: `vpengine bench paper` into $OUT under a time limit, printing only its result lines
paper() {
  local t=$1; shift
  timeout "$t" python3 -m vpengine.cli.main bench paper --out "$OUT" "$@" 2>&1 | grep -v "RANDOM\|WARNING" \
    | grep "E1 N=\|E2 N=\|MPS daemon\|Error\|error" | tail -4
}
