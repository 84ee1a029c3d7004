#!/usr/bin/env bash
# Set up .venv on a fresh machine, pinned by requirements/constraints.txt (refresh: make lock).
#   scripts/bootstrap.sh          what serving needs
#   scripts/bootstrap.sh --test   also the dev tools, the ray, bench and docs extras and the system packages
#                                 the tests drive (Chromium)
#   scripts/bootstrap.sh --docs   what serving needs and the docs extra (make docs: mkdocs), no warm-up
# PyTorch: the CPU build from PyTorch's own CPU index where it is reachable (PyPI's torch wheel for
# Linux is the CUDA build, several GB), else the machine's own torch==2.13.0 wheel. EDMCGS_TORCH_SPEC
# brings another build (e.g. EDMCGS_TORCH_SPEC=torch==2.13.0 EDMCGS_TORCH_INDEX= for CUDA from PyPI).
# Idempotent: a stamp keyed on the pins, this script and the mode skips the pip work (and edmcgs warm-up,
# which compiles the numba kernels into numba's cache) when nothing changed.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
TORCH_SPEC=${EDMCGS_TORCH_SPEC:-torch==2.13.0}
TORCH_INDEX=${EDMCGS_TORCH_INDEX-https://download.pytorch.org/whl/cpu}
mode=serve extras=""
case "${1:-}" in
  --test) mode=test extras="[dev,ray,bench,docs]" ;;
  --docs) mode=docs extras="[docs]" ;;
esac

if [[ $mode == test ]] && ! command -v chromium >/dev/null 2>&1; then
  if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null 2>&1; then
    echo "bootstrap: installing Debian's chromium for the browser viewer tests"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
  else
    echo "bootstrap: chromium not found and cannot apt-get it; the browser test will fail" >&2
  fi
fi

stamp=.venv/.bootstrap-$mode
want=$(cat pyproject.toml requirements/constraints.txt "$0" | sha256sum | cut -c1-16)
if [[ -f $stamp && $(cat "$stamp") == "$want" ]]; then
  exit 0
fi
[[ -x .venv/bin/python ]] || "$PYTHON" -m venv .venv
pip=(.venv/bin/python -m pip install -q --disable-pip-version-check)
"${pip[@]}" --upgrade "pip==$(sed -n 's/^pip==//p' requirements/constraints.txt)"
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  if [[ -n $TORCH_INDEX ]] && "${pip[@]}" --index-url "$TORCH_INDEX" --timeout 5 --retries 0 "$TORCH_SPEC" 2>/dev/null; then
    echo "bootstrap: $TORCH_SPEC from $TORCH_INDEX"
  else
    echo "bootstrap: $TORCH_SPEC from the default index (${TORCH_INDEX:-none given} unreachable or empty)"
    "${pip[@]}" "$TORCH_SPEC"
  fi
fi
"${pip[@]}" -c requirements/constraints.txt -e ".$extras"
# The numba kernels into numba's on-disk cache, so that the first edmcgs-serve / edmcgs train starts at
# once instead of compiling for a minute; seconds when the cache already holds them. The docs need none.
if [[ $mode != docs ]]; then
  echo "bootstrap: compiling the numba kernels once (about a minute the first time)"
  .venv/bin/edmcgs warm-up
fi
echo "$want" > "$stamp"
echo "bootstrap: .venv ready for $mode ($(.venv/bin/python -c 'import torch; print("torch", torch.__version__)'))"
