# One command sets everything up and runs the main job (`make demo`), one runs the tests (`make test`).
# Both are idempotent: set-up is skipped when .venv is current with pyproject.toml.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.msmem-installed
TORCH := torch==2.13.0

.PHONY: setup system-deps demo test test-slow lint perf clean

setup: system-deps $(STAMP)

# System libraries: open3d needs libusb-1.0. Installed with apt when missing (Debian; root or sudo).
system-deps:
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then \
	  echo "installing libusb-1.0 (needed by open3d)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi

# The venv; torch is pinned first so pip takes the CPU build instead of pulling a multi-GB CUDA one.
$(STAMP): pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip "setuptools>=77" wheel
	$(PY) -m pip install -q $(TORCH)
	$(PY) -m pip install -q -e ".[dev]"
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/msmem run --out runs/demo

test: setup
	$(PY) -m pytest -q -m "not slow"

test-slow: setup
	$(PY) -m pytest -q -m slow

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

perf: setup
	$(VENV)/bin/msmem perf ig

clean:
	rm -rf $(VENV) runs .pytest_cache .mypy_cache .ruff_cache
