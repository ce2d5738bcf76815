# phantom-calib — developer and user entry points.
# `make demo` and `make test` work on a fresh machine: they create .venv and install
# everything pinned in constraints.txt (torch: the CPU build, never a CUDA build).

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-out
PYTEST_ARGS ?=
# the suite runs on TEST_WORKERS pytest-xdist workers of one BLAS/OpenMP thread each (CI's
# 2 cores; each test file on one worker, tests/conftest.py); TEST_WORKERS=0: one process
TEST_WORKERS ?= 2
XDIST := $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)
ONE_THREAD := $(if $(XDIST),OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1)

.PHONY: all venv demo test test-all validate notebooks lab bench lint clean sysdeps

all: test

sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		SUDO=""; [ "$$(id -u)" = "0" ] || SUDO="sudo"; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@if ! command -v chromium >/dev/null 2>&1; then \
		echo "installing chromium (headless WebGL for the browser view's tests)"; \
		SUDO=""; [ "$$(id -u)" = "0" ] || SUDO="sudo"; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq chromium >/dev/null; \
	fi

$(STAMP): pyproject.toml constraints.txt
	@$(MAKE) --no-print-directory sysdeps
	@[ -x $(PY) ] || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[nn,sweep,dev]'
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	bash examples/demo.sh $(DEMO_OUT)

test: $(STAMP)
	$(ONE_THREAD) $(PY) -m pytest -q $(XDIST) $(PYTEST_ARGS)

test-all: $(STAMP)
	$(ONE_THREAD) $(PY) -m pytest -q -m "slow or not slow" $(XDIST) $(PYTEST_ARGS)

# the reproducible validation suite: the whole chain on fixed-seed twins, asserted bars,
# a JSON artefact of every figure in validation-out/
validate: $(STAMP)
	$(PY) -m pytest -q -m "validation" tests/validation $(PYTEST_ARGS)

NOTEBOOKS := $(wildcard examples/0*.py)
NB_OUT ?= examples/out

# execute every example notebook in order (PHANTOM_CALIB_SIZE=tiny|quick|dissertation)
# and render each to HTML in $(NB_OUT)/<size>/html
notebooks: $(STAMP)
	$(PY) -m pip install -q -c constraints.txt -e '.[notebook]'
	$(VENV)/bin/jupytext --sync $(NOTEBOOKS)
	cd examples && PHANTOM_CALIB_OUT=$(abspath $(NB_OUT))/$${PHANTOM_CALIB_SIZE:-quick} \
		../$(VENV)/bin/jupyter nbconvert \
		--to html --execute --ExecutePreprocessor.timeout=7200 \
		--output-dir $(abspath $(NB_OUT))/$${PHANTOM_CALIB_SIZE:-quick}/html \
		$(notdir $(NOTEBOOKS:.py=.ipynb))

lab: $(STAMP)
	$(PY) -m pip install -q -c constraints.txt -e '.[notebook]'
	$(VENV)/bin/jupyter lab examples/

bench: $(STAMP)
	$(PY) -m pip install -q -c constraints.txt -e '.[bench]'
	$(PY) benchmarks/bench_fem.py
	$(PY) benchmarks/bench_twin.py --presets quick
	$(PY) benchmarks/bench_calib.py --presets quick

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check fem calib registration imaging nn tests benchmarks examples
	$(VENV)/bin/lint-imports

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .ruff_cache *.egg-info
