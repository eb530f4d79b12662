# Sourced at the start of every GPU-machine command (see /work/.library/device/README.md):
# installs the carried cp312 wheels (pydantic) and puts the source tree on the path.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  || { echo "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD/src:$PWD/tests
export PYTHONUNBUFFERED=1
mkdir -p "${OUT:-/tmp/out}"
