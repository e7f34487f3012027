# Every target creates .venv when it is missing, so a fresh clone needs only `make demo`
# or `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench lint clean

setup: $(STAMP)

# Open3D's wheel links against libusb-1.0 at import time; Debian does not ship it by default.
$(STAMP): pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
		if [ "$$(id -u)" = "0" ]; then \
			(apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
			 (apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null)); \
		else \
			echo "cavenav needs libusb-1.0 for Open3D: run 'sudo apt-get install -y libusb-1.0-0'"; exit 1; \
		fi; \
	fi
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,transformers,ray]'
	touch $(STAMP)

demo: setup
	$(BIN)/cavenav run S4 --pilot geometric

test: setup
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/python benchmarks/sensor_step.py
	$(BIN)/python benchmarks/sweep.py

lint: setup
	$(BIN)/ruff check src tests benchmarks

clean:
	rm -rf $(VENV) runs
