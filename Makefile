# One command sets everything up and runs the main job (`make demo`), one runs the tests (`make test`).
# Both are idempotent: set-up is skipped when .venv is current with pyproject.toml.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.msmem-installed
TORCH := torch==2.13.0

.PHONY: setup system-deps demo test test-unit test-slow lint perf docs docs-site clean sapien test-sapien test-ray mutation

setup: system-deps $(STAMP)

# System libraries: open3d needs libusb-1.0; the report test renders report.html in headless Chromium.
# Installed with apt when missing (Debian; root or sudo).
system-deps:
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then \
	  echo "installing libusb-1.0 (needed by open3d)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@if ! command -v chromium >/dev/null 2>&1; then \
	  echo "installing chromium (headless, for the run report test)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium >/dev/null; \
	fi

# The venv; torch is pinned first so pip takes the CPU build instead of pulling a multi-GB CUDA one. The
# numba kernels are compiled here, not in the first demo or test run: five steps of `ours` with pushes and
# grasps proposed from step 1 (about a minute once; the same episode then takes 17 s), then one decision
# timed against the brute-force references (their kernels, about 25 s), compile 26 of the 40.
$(STAMP): pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip "setuptools>=77" wheel
	$(PY) -m pip install -q $(TORCH)
	$(PY) -m pip install -q -e ".[dev]"
	@echo "compiling the numba kernels once (a five-step episode and one timed decision, about 1.5 minutes; cached beside the sources)"
	$(VENV)/bin/msmem run --steps 5 --scene msmem_core/suites/hard25/scene_07.json \
	  -c examples/manipulate-from-step-1.yaml --out $(VENV)/warm-up --overwrite --no-report -q >/dev/null
	@rm -rf $(VENV)/warm-up
	$(VENV)/bin/msmem perf step --repeats 1 --beliefs 1 --scene msmem_core/suites/hard25/scene_07.json \
	  --views 4 >/dev/null
	$(PY) -c "import matplotlib.pyplot"
	@touch $(STAMP)

# The demo runs `ours` under the library defaults (msmem_core/presets/defaults.yaml: the learned whole-map
# observation model and the effect models fine-tuned on its beliefs; README, "make demo");
# `make demo DEMO_CONFIG=examples/analytic.yaml` runs the analytic update and its effect models instead.
DEMO_CONFIG ?=

demo: setup
	$(VENV)/bin/msmem run --out runs/demo --overwrite $(if $(DEMO_CONFIG),-c $(DEMO_CONFIG))

# Two workers (pytest-xdist), a test file per worker: each file's module fixtures are built once.
test: setup
	$(PY) -m pytest -q -m "not slow" -n 2 --dist loadfile

# The fast tier: the math, the core's loop and data types (tests/conftest.py, UNIT_MODULES).
test-unit: setup
	$(PY) -m pytest -q -m "unit and not slow" -n 2 --dist loadfile

test-slow: setup
	$(PY) -m pytest -q -m slow -n 2 --dist loadfile

# Optional SAPIEN backend (not part of `make test`'s install): the extra, and a CPU Vulkan driver
# (Mesa 25 lavapipe, unpacked into .venv/lavapipe; no system package changes) for SAPIEN's own
# renderer. Without the driver the backend uses its ray-cast camera. See docs/how-to/use-sapien.md.
sapien: setup
	$(PY) -m pip install -q -e ".[dev,sapien]"
	bash simulators/msmem_sapien/setup_lavapipe.sh || echo "lavapipe not set up: the SAPIEN backend will use its ray-cast camera"
	$(PY) -m msmem_sapien

test-sapien: sapien
	$(PY) -m pytest -q tests/test_sapien_sim.py tests/test_arm_execution.py

# Optional Ray executor: local and Ray runs of the benchmark must give identical tables.
test-ray: setup
	$(PY) -m pip install -q -e ".[dev,ray]"
	$(PY) -m pytest -q tests/test_bench.py tests/test_faults_bench.py -k ray

# Mutation testing of the metrics (mutmut; about 2 minutes on 2 cores): prints killed / survived counts.
mutation: setup
	$(PY) -m pip install -q -e ".[dev,mutation]"
	rm -rf mutants
	$(VENV)/bin/mutmut run > /dev/null 2>&1 || true
	$(VENV)/bin/mutmut results --all true | awk -F': ' '{print $$2}' | sort | uniq -c

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

perf: setup
	$(VENV)/bin/msmem perf ig

# The generated references (a test fails when they drift from the code).
docs: setup
	$(VENV)/bin/msmem docs config > docs/reference/config.md
	$(VENV)/bin/msmem docs cli > docs/reference/cli.md
	$(VENV)/bin/msmem docs api > docs/reference/api.md
	$(VENV)/bin/msmem docs results > docs/results.md

# The manual as a website (mkdocs.yml; the optional `docs` extra, installed here when missing) in site/.
# --strict fails on a broken link or anchor, and on a page in neither the nav nor `not_in_nav`.
docs-site: setup
	@$(VENV)/bin/python -c "import mkdocs, material, mkdocstrings_handlers.python" 2>/dev/null \
	  || $(PY) -m pip install -q -e ".[docs]"
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) runs mutants site .pytest_cache .mypy_cache .ruff_cache
