# fleetmap: every target creates .venv/ with the project installed when it is missing.
# `make demo` runs the main job, `make test` the tests; see README.md.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
# The service and its commands (what `make demo` and `make serve` need), then the test and benchmark
# tools on top (pytest, hypothesis, ruff, mypy, playwright, schemathesis, pyoctomap) for the targets that
# use them: a first `make demo` does not wait for those.
STAMP := $(VENV)/.installed
DEV_STAMP := $(VENV)/.installed-test
# Debian packages the test suite uses: Chromium for the web viewer's end-to-end test; curl and
# unzip for the examples of docs/api.md, which tests/test_docs.py runs as written.
SYSTEM_PACKAGES ?= chromium curl unzip
# Test processes (pytest-xdist): most tests wait on a real service they started, so three share a
# 2-core machine well (1476 tests: 11 min in three, using 167 % of the two cores, against 12-13 min
# in two). `make test TEST_WORKERS=0` runs them in one process, in file order.
# The run ends with its 20 slowest tests: CI's log shows what keeps it within its 15-minute budget.
TEST_WORKERS ?= 3

.PHONY: demo serve test bench bench-service soak lint format clean system-deps

# pyproject.toml's requires-python, checked before the venv is made: pip's refusal came only after
# the venv of the old Python was made, and that venv stayed (`make demo PYTHON=python3.12` used it
# again) until the user deleted it. Exits 1 saying so (Python 2's syntax too: no f-string).
NEW_ENOUGH := import sys; sys.exit(0 if sys.version_info >= (3, 11) else "fleetmap: needs Python 3.11 or newer, and %s is Python %s: give one, e.g. make demo PYTHON=python3.12" % (sys.executable, sys.version.split()[0]))

# A first install interrupted (Ctrl-C, a closed terminal) while venv ran ensurepip left a
# .venv/bin/python without pip, and every later run stopped at "No module named pip" until the user
# found and deleted .venv/: a .venv whose pip does not run, or of too old a Python, is made again.
$(STAMP): pyproject.toml
	@echo "fleetmap: installing fleetmap and its dependencies into $(VENV)/ (from PyPI: a few minutes, the first time)"
	@$(PY) -c '$(NEW_ENOUGH)' >/dev/null 2>&1 && $(PY) -m pip --version >/dev/null 2>&1 || \
	  { $(PYTHON) -c '$(NEW_ENOUGH)' && $(PYTHON) -m venv --clear $(VENV); }
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e .
	@touch $(STAMP)

$(DEV_STAMP): $(STAMP)
	@echo "fleetmap: adding the test and benchmark tools to $(VENV)/ (a few minutes, the first time)"
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $(DEV_STAMP)

# Debian packages the tests need (you are root on the test machines). Skipped when already there.
system-deps:
	@bash scripts/system-deps.sh $(SYSTEM_PACKAGES)

demo: $(STAMP)
	$(VENV)/bin/fleetmap demo $(DEMO_ARGS)

# The project's modules compiled to bytecode once, before the run: every process the tests start
# (some 600 services, robots and commands) imports them, and where PYTHONDONTWRITEBYTECODE is set
# (the development machines set it) each compiled them from source again: 0.12 s of CPU a process.
test: $(DEV_STAMP) system-deps
	$(VENV)/bin/ruff check service tests clients scripts benchmarks
	$(VENV)/bin/ruff format --check service tests clients scripts benchmarks
	$(VENV)/bin/mypy
	$(PY) -m compileall -q service clients
	$(PY) -m pytest -q -n $(TEST_WORKERS) --durations=20

serve: $(STAMP)
	$(VENV)/bin/fleetmap serve $(SERVE_ARGS)

bench: $(DEV_STAMP)
	$(PY) benchmarks/bench_engine.py

bench-service: $(DEV_STAMP)
	$(PY) benchmarks/bench_service.py

# The crash tests' long form (a few minutes, not part of `make test`, which runs them with 2 and 4
# kills): 12 SIGKILLs / SIGTERMs at random moments of a durable service while robots publish.
SOAK_ROUNDS ?= 12
soak: $(DEV_STAMP)
	FLEETMAP_SOAK_ROUNDS=$(SOAK_ROUNDS) $(PY) -m pytest -q -n 0 -p no:cacheprovider \
		tests/test_crash_exactly_once.py \
		tests/test_durability.py::test_kill_9_at_random_moments_loses_nothing_reported

lint: $(DEV_STAMP)
	$(VENV)/bin/ruff check service tests clients scripts benchmarks
	$(VENV)/bin/ruff format --check service tests clients scripts benchmarks
	$(VENV)/bin/mypy

format: $(DEV_STAMP)
	$(VENV)/bin/ruff format service tests clients scripts benchmarks

# The installed tools and their caches. Not the maps: ./fleetmap-data, nor out/, where the README's
# `fleetmap build` writes (an earlier `make demo` built its map there, and this removed it).
clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache
