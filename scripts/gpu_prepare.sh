#!/usr/bin/env bash
# Gather in .gpu/ (ignored by git) what scripts/gpu_check.sh needs on a GPU machine that reaches no
# package index: the wheels of what it lacks (its image has torch, numba, h5py, numpy, pytest, httpx,
# pillow, msgpack, prometheus-client, rich, jaxtyping, ninja), at this repository's pins, for CPython 3.12
# on x86-64 Linux; and the 346x260 street the `real` preset's figures are measured on
# (edmcgs synth traffic --fps 5 --seconds 3 --seed 0, as in the README's traffic table).
# Left out, to stay within what travels with a device call (64 MiB with the repository): the wheels of the
# sources no check opens (dv-processing, faery, rosbags, pyusb: AEDAT, DAVIS, Prophesee, ROS) and pycolmap.
#   scripts/gpu_prepare.sh        # about a minute; then run scripts/gpu_check.sh there (its header)
# GPU_WHEELS (default .gpu/wheels) and GPU_PYTHON_VERSION (default 3.12, the machine's) gather a set for
# another interpreter, e.g. this machine's to check gpu_check.sh here.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
WHEELS=${GPU_WHEELS:-.gpu/wheels}
VERSION=${GPU_PYTHON_VERSION:-3.12}
WANT=(fastapi starlette pydantic pydantic_core annotated-types annotated-doc typing-inspection typing_extensions
      opentelemetry-api fastapi-offline uvicorn httptools websockets pydantic-settings python-dotenv plyfile gsplat
      setuptools)
mkdir -p "$WHEELS"
rm -f "$WHEELS"/*.whl
for name in "${WANT[@]}"; do
  pin=$(grep -i -E "^${name//[-_]/[-_]}==" requirements/constraints.txt) \
    || { echo "gpu_prepare: $name is not pinned in requirements/constraints.txt" >&2; exit 1; }
  "$PY" -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: --python-version "$VERSION" \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d "$WHEELS" "$pin"
done
if [[ ! -f .gpu/traffic.h5 ]]; then
  .venv/bin/edmcgs synth traffic --fps 5 --seconds 3 --seed 0 -q -o .gpu/traffic.h5
fi
echo "gpu_prepare: $(ls "$WHEELS" | wc -l) wheels in $WHEELS, and .gpu/traffic.h5 ($(du -sh .gpu | cut -f1) in .gpu)"
