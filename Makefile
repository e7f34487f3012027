# Every target creates .venv when it is missing, so a fresh clone needs only `make demo`
# or `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
# setup: cavenav and what it needs to fly (what `make demo` needs);
# setup-test: plus pytest, transformers with torch (CPU), Ray, the train extra (datasets,
# accelerate, peft) and the docs extra (MkDocs), for `make test`.
STAMP := $(VENV)/.installed
TEST_STAMP := $(VENV)/.installed-test
DOCS_STAMP := $(VENV)/.installed-docs

.PHONY: setup setup-test demo test docs bench mutate lint clean

setup: $(STAMP)
setup-test: $(TEST_STAMP)

# Open3D's wheel links against libusb-1.0 at import time; Debian does not ship it by default.
# Numba's OpenMP threading layer needs libgomp; without it Numba falls back to its work
# queue, on which frames are shaded one at a time (cavenav.sensors.kernels).
$(STAMP): pyproject.toml
	@export PATH="$$PATH:/usr/sbin:/sbin"; missing=""; \
	ldconfig -p 2>/dev/null | grep -q libusb-1.0 || missing="libusb-1.0-0"; \
	ldconfig -p 2>/dev/null | grep -q libgomp.so.1 || missing="$$missing libgomp1"; \
	if [ -n "$$missing" ] && [ "$$(id -u)" = "0" ]; then \
		apt-get install -y -q $$missing >/dev/null 2>&1 || \
		(apt-get update -q >/dev/null && apt-get install -y -q $$missing >/dev/null) || true; \
	fi; \
	if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
		echo "cavenav needs libusb-1.0 for Open3D: run 'sudo apt-get install -y libusb-1.0-0'"; exit 1; \
	fi; \
	ldconfig -p 2>/dev/null | grep -q libgomp.so.1 || \
		echo "cavenav: no libgomp, so frames shade one at a time (sudo apt-get install -y libgomp1)"
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e .
	@# numba compiles the sensor kernels on first use (about a minute); do it now, once.
	$(BIN)/cavenav warmup
	touch $(STAMP)

$(TEST_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -e '.[test,transformers,ray,train,docs]'
	touch $(TEST_STAMP)

$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -e '.[docs]'
	touch $(DOCS_STAMP)

demo: setup
	$(BIN)/cavenav run S4 --pilot geometric

# The checks first (a minute), then the site with warnings as errors (a few seconds), then
# the suite, a test file to each worker in turn (a file's module fixtures, a cave or a
# model, are built once). Three workers on two cores: the flights through the fake
# autopilot and the sweeps' worker processes wait much of their time, and a third worker
# fills it (measured on 2 cores: 8.6 minutes, against 9.9 with two).
test: lint docs
	$(BIN)/python -m pytest -q -n 3 --dist loadfile

# The documentation site (mkdocs.yml, docs/, the API reference from the docstrings) into
# site/. --strict: a warning (a broken link or anchor, a docstring naming a parameter the
# function lacks) fails the build, in CI too. NO_MKDOCS_2_WARNING only quiets the theme's
# end-of-life banner (Material for MkDocs: critical fixes until May 2027).
docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

bench: setup-test
	$(BIN)/python benchmarks/sensor_step.py
	$(BIN)/python benchmarks/episode.py
	$(BIN)/python benchmarks/sweep.py
	$(BIN)/python benchmarks/env_steps.py
	$(BIN)/python benchmarks/big_mesh.py
	$(BIN)/python benchmarks/mavlink_action.py

# Mutation testing of the shield, the action grammar and the reply parser (not in CI).
mutate: setup-test
	$(BIN)/python -m pip install -q mutmut==3.8.1
	$(BIN)/python benchmarks/mutation.py

# Lint, format and type checks: CI runs them on every clean clone, through `make test`.
lint: setup-test
	$(BIN)/ruff check src tests benchmarks examples
	$(BIN)/ruff format --check src tests benchmarks examples
	$(BIN)/mypy

clean:
	rm -rf $(VENV) runs .mutation site
