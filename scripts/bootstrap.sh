#!/usr/bin/env bash
# Set up .venv on a fresh machine: the local CPU build of torch first (an unpinned torch would pull
# several GB of CUDA wheels), then this project, editable, with its dev extras. Idempotent: a stamp
# keyed on pyproject.toml and this script skips the pip work when nothing changed.
#   scripts/bootstrap.sh          service + dev tools
#   scripts/bootstrap.sh --test   also the system packages the test suite drives (headless Chromium)
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
TORCH_SPEC=${EDMCGS_TORCH_SPEC:-torch==2.13.0}   # GPU users: EDMCGS_TORCH_SPEC=torch (or their build)

if [[ "${1:-}" == "--test" ]] && ! command -v chromium >/dev/null 2>&1; then
  if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null 2>&1; then
    echo "bootstrap: installing Debian's chromium for the browser viewer tests"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
  else
    echo "bootstrap: chromium not found and cannot apt-get it; the browser test will fail" >&2
  fi
fi

stamp=.venv/.bootstrap-stamp
want=$(cat pyproject.toml "$0" | sha256sum | cut -c1-16)
if [[ -f $stamp && $(cat "$stamp") == "$want" ]]; then
  exit 0
fi
[[ -x .venv/bin/python ]] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q "$TORCH_SPEC"
.venv/bin/python -m pip install -q -e '.[dev]'
echo "$want" > "$stamp"
echo "bootstrap: .venv ready ($(.venv/bin/python -c 'import torch; print("torch", torch.__version__)'))"
