#!/usr/bin/env bash
# Fuzz the HTTP API with schemathesis (all checks, positive and negative data, >= 1000 cases) against
# a real edmcgs-serve on a tiny synthetic scene, then require 0 responses with a 5xx status.
#
#   scripts/fuzz_api.sh [MAX_EXAMPLES]      # default 1200 per operation (1323 cases with seed 1)
#
# Installs the fuzz extra (schemathesis, pinned in pyproject.toml) into .venv first.
# scripts/schemathesis.toml says which statuses schema-valid data may still get, and why.
set -euo pipefail
cd "$(dirname "$0")/.."
max_examples="${1:-1200}"
.venv/bin/python -m pip install -q --disable-pip-version-check -c requirements/constraints.txt -e '.[dev,fuzz]'
work="$(mktemp -d)"
port="$(.venv/bin/python -c 'from harness.server import free_port; print(free_port())')"
.venv/bin/python -c "
from harness.server import build_scene, WIDTH, HEIGHT
build_scene('$work', width=WIDTH, height=HEIGHT, event_rate=20_000, init_points=2000, control_points=64)"
.venv/bin/edmcgs-serve --replay "$work/scene.h5" --checkpoint "$work/scene.ckpt" --loop --port "$port" \
    > "$work/server.log" 2>&1 &
server=$!
trap 'kill -INT $server 2>/dev/null; wait $server 2>/dev/null; rm -rf "$work"' EXIT
for _ in $(seq 120); do curl -sf "http://127.0.0.1:$port/healthz" > /dev/null && break; sleep 1; done
(cd "$work" && "$OLDPWD/.venv/bin/st" --config-file "$OLDPWD/scripts/schemathesis.toml" run \
    "http://127.0.0.1:$port/openapi.json" --checks all --mode all --max-examples "$max_examples" \
    --workers 1 --seed 1)
fivexx="$(curl -s "http://127.0.0.1:$port/metrics" | grep '^edmcgs_http_requests_total' \
          | grep -c 'code="5' || true)"
echo "5xx series: $fivexx"
test "$fivexx" = 0
