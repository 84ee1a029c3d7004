#!/usr/bin/env bash
# The GPU figures and CUDA tests in one command on a fresh GPU machine: installs what the machine lacks
# from the wheels in .gpu/ (scripts/gpu_prepare.sh gathers them, and the 346x260 street), installs this
# repository (editable, without dependencies: the machine brings torch, numba, h5py), builds gsplat's
# CUDA extension (about 80 s on 16 cores; the build is left in $OUT/gsplat_cuda.so.gz, and a copy of it
# in .gpu/ is loaded instead of building again on the same image), then runs bench.gpu into $OUT:
# gpu.json (every part's figures), gpu.log (their output), setup.log (this script's). Arguments go to
# bench.gpu (--parts tests,render,...; --deadline). Everything ends within GPU_CHECK_SECONDS (default 585).
#
#   scripts/gpu_prepare.sh                               # here, once (.gpu/ is ignored by git)
#   device run: command "bash scripts/gpu_check.sh", carry [".gpu"], timeout_s 600
#
# Without a GPU, to check this script and the driver with CPU-sized settings, in a venv of this machine's
# Python holding only what the GPU machine has (GPU_WHEELS: a wheel set for its version, gpu_prepare.sh):
#   OUT=/tmp/gpu PYTHON=VENV/bin/python GPU_WHEELS=DIR scripts/gpu_check.sh --device cpu --tiny
set -uo pipefail
cd "$(dirname "$0")/.."
start=$SECONDS
limit=${GPU_CHECK_SECONDS:-585}
OUT=${OUT:?set OUT to the folder for the results}
PY=${PYTHON:-python3}
WHEELS=${GPU_WHEELS:-.gpu/wheels}
export PYTHONUNBUFFERED=1
mkdir -p "$OUT"
[[ -f .gpu/traffic.h5 && -d $WHEELS ]] || { echo "gpu_check: run scripts/gpu_prepare.sh first" >&2; exit 2; }

setup() {
  set -e
  date -u
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv || echo "no nvidia-smi"
  "$PY" -m pip install -q --disable-pip-version-check --no-index --no-deps --no-compile --no-cache-dir \
    "$WHEELS"/*.whl
  "$PY" -m pip install -q --disable-pip-version-check --no-index --find-links "$WHEELS" --no-deps -e .
  "$PY" -c "import edmcgs.server.app, edmcgs.model.train.trainer, torch; print('torch', torch.__version__, \
'cuda', torch.version.cuda, 'available', torch.cuda.is_available())"
  if "$PY" -c "import sys, torch; sys.exit(not torch.cuda.is_available())"; then
    if [[ -f .gpu/gsplat_cuda.so.gz ]]; then  # the extension an earlier run built on the same image
      mkdir -p /tmp/gsplat_prebuilt
      gunzip -c .gpu/gsplat_cuda.so.gz > /tmp/gsplat_prebuilt/gsplat_cuda.so
      # gsplat imports `gsplat.csrc` before it compiles anything: this module is that import
      cat > "$("$PY" -c "import gsplat, os; print(os.path.dirname(gsplat.__file__))")/csrc.py" <<'PY'
import sys
try:
    from torch.utils.cpp_extension import _import_module_from_library
    sys.modules[__name__] = _import_module_from_library("gsplat_cuda", "/tmp/gsplat_prebuilt", True)
except Exception as exc:  # gsplat catches ImportError alone, then builds the extension itself
    raise ImportError(f"the carried gsplat extension does not load: {exc}") from exc
PY
    fi
    echo "building gsplat's CUDA extension (at most 300 s)"
    t0=$SECONDS
    if MAX_JOBS=${MAX_JOBS:-16} timeout 300 "$PY" -c "from gsplat.cuda._backend import _C; assert _C is not None"
    then
      echo "gsplat's extension ready after $((SECONDS - t0)) s"
      built=$("$PY" -c "from torch.utils.cpp_extension import _get_build_directory as d; \
print(d('gsplat_cuda', False))")/gsplat_cuda.so
      if [[ -f $built ]]; then gzip -c "$built" > "$OUT/gsplat_cuda.so.gz"; fi  # for .gpu/: no build next time
    else  # uninstalled, so that no later process tries the build again: CUDA renders take the torch path
      echo "gsplat's extension NOT built after $((SECONDS - t0)) s: uninstalling gsplat"
      "$PY" -m pip uninstall -q -y gsplat
    fi
  fi
}
(setup) > "$OUT/setup.log" 2>&1
status=$?
tail -n 5 "$OUT/setup.log"
if [[ $status -ne 0 ]]; then
  echo "gpu_check: setup failed ($status): $OUT/setup.log" >&2
  exit $status
fi
"$PY" -m bench.gpu --out "$OUT" --real .gpu/traffic.h5 --deadline $((limit - (SECONDS - start))) "$@"
