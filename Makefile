# DriveTrack Release: every target creates or reuses the virtual environment .venv itself.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | sha256sum | cut -c1-12)
export PREFECT_HOME ?= $(CURDIR)/.prefect
export DO_NOT_TRACK := 1
export PREFECT_SERVER_ANALYTICS_ENABLED := false
export DASK_LOGGING__DISTRIBUTED := warning

.PHONY: help venv system-deps test bench release serve demo clean

help:
	@echo "make test [TEST_WORKERS=n]     run the test suite (creates .venv) in n processes (default: one"
	@echo "                               per core, at most 4; 0: in this process)"
	@echo "make release VERSION=x.y.z     build and publish a release on embedded defaults"
	@echo "        [SOURCE=url] [STORE=url] [SEGMENTS='id ...'] [SPLITS=training] [NPZ=1: also publish npz clips]"
	@echo "make serve                     serve the scheduled regeneration deployment"
	@echo "make bench                     run the benchmarks (results in docs/benchmarks.md)"

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	# torch 2.13.0 CPU lies on the project machines' disk (no GPU here); install it first so that
	# the torch extra's range is already satisfied and no multi-GB CUDA build is pulled in.
	# Keep the interpreter's pip: newer pips skip the machine's constraints and pick CUDA builds.
	$(PY) -m pip install -q torch==2.13.0 || $(PY) -m pip install -q "torch>=2.3,<2.15"
	$(PY) -m pip install -q -e ".[test,torch]"
	@rm -f $(VENV)/.installed-*
	@touch $(STAMP)

venv: $(STAMP)

# Debian's chromium renders the status page in the browser test. Installed when missing and we
# may (root with apt-get, as on the project machines and CI); elsewhere, and when apt-get fails
# or the network hangs (each apt-get is bounded by APT_TIMEOUT seconds), that one test is
# skipped with its reason (pytest -rs prints it) and make goes on.
APT_TIMEOUT ?= 300
CHROMIUM ?= chromium
APT_OPTS := -o Acquire::http::Timeout=30 -o Acquire::https::Timeout=30 -o Acquire::Retries=1
system-deps:
	@if ! command -v $(CHROMIUM) >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing Debian's chromium for the status-page browser test (at most $(APT_TIMEOUT) s per step)"; \
	    (timeout -k 10 $(APT_TIMEOUT) apt-get $(APT_OPTS) update -qq \
	      && DEBIAN_FRONTEND=noninteractive timeout -k 10 $(APT_TIMEOUT) apt-get $(APT_OPTS) install -y -qq chromium >/dev/null) \
	      || echo "warning: could not install chromium (offline? apt-get failed or timed out); the browser test will be skipped"; \
	  else echo "note: chromium not installed; the browser test will be skipped"; fi; \
	fi

# The test files are shared among TEST_WORKERS processes (pytest-xdist; "auto": one per core, at
# most 4, each holding its own session fixtures); a file's tests stay together in one process, in
# their order, so a module's fixtures are built once. TEST_WORKERS=0 runs them all in this process.
TEST_WORKERS ?= auto
test: $(STAMP) system-deps
	$(PY) -m pytest -q -rs -p no:cacheprovider -n $(TEST_WORKERS) --maxprocesses=4 --dist loadfile

bench: $(STAMP)
	$(PY) -m bench.run $(BENCH)

release:
	@if [ -z "$(VERSION)" ]; then \
	  echo "usage: make release VERSION=x.y.z [SOURCE=url] [STORE=url] [SEGMENTS='id ...'] [SPLITS=training] [NPZ=1]" >&2; \
	  echo "  with only VERSION: synthesises a small source into ./data/synthetic, publishes to ./store" >&2; \
	  exit 2; fi
	@$(MAKE) --no-print-directory venv
	$(PY) -m flows.release --version "$(VERSION)" --store "$(or $(STORE),./store)" --splits "$(or $(SPLITS),training)" \
	  $(if $(SOURCE),--source "$(SOURCE)") $(if $(SEGMENTS),--segments "$(SEGMENTS)") $(if $(NPZ),--npz)

serve: $(STAMP)
	$(PY) -m flows.serve --store "$(or $(STORE),./store)" $(if $(SOURCE),--source "$(SOURCE)") $(if $(CRON),--cron "$(CRON)")

clean:
	rm -rf $(VENV) .pytest_cache
