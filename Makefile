# fleetmap: every target creates .venv/ with the project installed when it is missing.
# `make demo` runs the main job, `make test` the tests; see README.md.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT ?= out
# Debian packages the test suite uses: Chromium for the web viewer's end-to-end test.
SYSTEM_PACKAGES ?= chromium

.PHONY: demo serve test bench bench-service lint format clean system-deps

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

# Debian packages the tests need (you are root on the test machines). Skipped when already there.
system-deps:
	@bash scripts/system-deps.sh $(SYSTEM_PACKAGES)

demo: $(STAMP)
	$(VENV)/bin/fleetmap demo $(DEMO_ARGS)

test: $(STAMP) system-deps
	$(VENV)/bin/ruff check service tests clients scripts benchmarks
	$(VENV)/bin/ruff format --check service tests clients scripts benchmarks
	$(PY) -m pytest -q

serve: $(STAMP)
	$(VENV)/bin/fleetmap serve $(SERVE_ARGS)

bench: $(STAMP)
	$(PY) benchmarks/bench_engine.py

bench-service: $(STAMP)
	$(PY) benchmarks/bench_service.py

lint: $(STAMP)
	$(VENV)/bin/ruff check service tests clients scripts benchmarks
	$(VENV)/bin/ruff format --check service tests clients scripts benchmarks

format: $(STAMP)
	$(VENV)/bin/ruff format service tests clients scripts benchmarks

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .ruff_cache
