# Sourced by the other scripts, from the repository root. Installs the carried cp312 wheels of .whl/ where there are
# any and the machine lacks pydantic (the GPU machine), puts this tree's src/ on the path and sets OUT, the results
# folder: $OUT if set, else benchmarks/results/<GPU kind> (h100, h200, ...). PYTHON: the interpreter (python3).
set -u
PYTHON=${PYTHON:-python3}
SITE=
# (asked without PYTHONPATH: a script sourcing this again, under one that did, must still put /tmp/site on the path)
if compgen -G ".whl/*.whl" >/dev/null && ! env -u PYTHONPATH "$PYTHON" -c "import pydantic" 2>/dev/null; then
  [ -d /tmp/site/pydantic ] \
    || "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
      .whl/*.whl || { echo "wheel install failed"; exit 1; }
  SITE=/tmp/site:
fi
export PYTHONPATH="$SITE$PWD/src:$PWD/tests"
export PYTHONUNBUFFERED=1
if [ -z "${OUT:-}" ]; then
  kind=$("$PYTHON" -c "import re, torch
n = torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'cpu'
m = re.search(r'\b([A-Z]+[0-9]+)\b', n)
print((m.group(1) if m else re.sub(r'\W+', '_', n)).lower())") || { echo "no GPU kind: set OUT"; exit 1; }
  OUT=benchmarks/results/$kind
fi
export OUT
mkdir -p "$OUT"

# vpengine ARGS...: the CLI of the tree on PYTHONPATH
vpengine() { "$PYTHON" -m vpengine.cli.main "$@"; }
