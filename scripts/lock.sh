#!/usr/bin/env bash
# Refresh requirements/constraints.txt: resolve the newest versions pyproject.toml allows in a scratch
# venv (CPU torch as the bootstrap installs it, the dev extras too) and pin them all. torch itself is
# left to the bootstrap (its build differs per machine: CPU, CUDA).
set -euo pipefail
cd "$(dirname "$0")/.."
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
"${PYTHON:-python3}" -m venv "$scratch/venv"
pip=("$scratch/venv/bin/python" -m pip install -q --disable-pip-version-check)
"${pip[@]}" --upgrade pip
"${pip[@]}" --index-url https://download.pytorch.org/whl/cpu --timeout 5 --retries 0 torch==2.13.0 2>/dev/null \
  || "${pip[@]}" torch==2.13.0
"${pip[@]}" -e '.[dev,ray,bench,docs]'
{
  echo "# Pinned versions of everything pyproject.toml installs (runtime, dev, ray, bench and docs extras), used"
  echo "# by scripts/bootstrap.sh and docker/Dockerfile. Refresh with: make lock"
  "$scratch/venv/bin/python" -m pip freeze --all --exclude-editable \
    | grep -viE '^(torch|nvidia-|triton|edmcgs)[=-]' | grep -v '^-e ' | sort -f
} > requirements/constraints.txt
echo "lock: requirements/constraints.txt has $(grep -vc '^#' requirements/constraints.txt) pins"
