# The two commands of the README, and the checks of CONTRIBUTING.md.
PY := .venv/bin/python

.PHONY: serve test check lint lock fuzz bench demo docs

serve:  ## set up, then serve the bundled demo scene on http://127.0.0.1:8000
	scripts/bootstrap.sh
	.venv/bin/edmcgs-serve

test:   ## set up, then run the whole test suite (two workers; the 25 slowest tests listed at the end)
	scripts/bootstrap.sh --test
	$(PY) -m pytest -n 2 --dist loadscope --durations=25

check:  ## the inner loop: everything but the slow end-to-end cases (real servers, the browser)
	scripts/bootstrap.sh --test
	$(PY) -m pytest -n 2 --dist loadscope -m "not slow" -q

docs:   ## the docs site into site/ (mkdocs.yml, pages in docs/, benchmark figures read from reports/), offline
	scripts/bootstrap.sh --docs
	.venv/bin/mkdocs build --strict

lint:
	.venv/bin/ruff check .

lock:   ## refresh requirements/constraints.txt to the newest versions pyproject.toml allows
	scripts/lock.sh

fuzz:   ## schemathesis against a real edmcgs-serve: all checks, >= 1000 cases, 0 server errors
	scripts/bootstrap.sh --test
	scripts/fuzz_api.sh

bench:  ## every benchmark, JSON into reports/bench/
	mkdir -p reports/bench
	for b in render sensor simulate serve poses; do $(PY) -m bench.$$b --json reports/bench/$$b.json || exit 1; done

demo:   ## regenerate the bundled demo scene (server/demo/) from the synthetic benchmark
	scripts/bootstrap.sh
	.venv/bin/edmcgs synth jumpingjack --fps 5 --size small --seed 0 --compress -q -o server/demo/scene.h5
	.venv/bin/edmcgs train server/demo/scene.h5 --config demo --force -o server/demo/scene.ckpt
