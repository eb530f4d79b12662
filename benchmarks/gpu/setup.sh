# Sourced at the start of every GPU-machine command (see /work/.library/device/README.md):
# installs the carried cp312 wheels (pydantic) and puts the source tree on the path.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  || { echo "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD/src:$PWD/tests
export PYTHONUNBUFFERED=1
mkdir -p "${OUT:-/tmp/out}"
# paper SECONDS ARGS...: `vpengine bench paper` into $OUT under a time limit, printing only its result lines
paper() {
  local t=$1; shift
  timeout "$t" python3 -m vpengine.cli.main bench paper --out "$OUT" "$@" 2>&1 | grep -v "RANDOM\|WARNING" \
    | grep "E1 N=\|E2 N=\|MPS daemon\|Error\|error" | tail -4
}
