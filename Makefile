# cpslam — `make test` and `make demo` set everything up on a fresh machine.
# Re-running on a ready machine installs nothing: the venv is rebuilt only when
# pyproject.toml changes (see $(STAMP)).

PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
# Where pip finds no local CPU wheel of torch, PyPI's default is a multi-GB CUDA build:
#   make test TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
TORCH_INDEX_URL ?=
PYTEST_ARGS ?=
DEMO_ARGS ?=
BIN := $(VENV)/bin
STAMP := $(VENV)/.cpslam-installed

.PHONY: help venv test test-fast lint format demo clean

help:
	@echo "make test      set up .venv if needed, ruff, then the whole test suite"
	@echo "make test-fast the suite without tests marked slow"
	@echo "make demo      set up .venv if needed, run the two-agent demo"
	@echo "make lint      ruff"
	@echo "make clean     remove .venv and caches"

venv: $(STAMP)

$(STAMP): pyproject.toml
	@# open3d needs Debian's libusb-1.0-0 at import time.
	@if command -v dpkg >/dev/null 2>&1 && ! dpkg -s libusb-1.0-0 >/dev/null 2>&1; then \
	  echo ">> installing libusb-1.0-0 (needed by open3d)"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV) || { \
	  echo ">> '$(PYTHON) -m venv' failed: on Debian/Ubuntu install python3-venv"; exit 1; }
	$(BIN)/python -m pip install -q --upgrade pip
	@# torch first and pinned: an unpinned torch pulls a multi-GB CUDA build.
	$(BIN)/python -m pip install -q "$(TORCH_SPEC)" \
	  $(if $(TORCH_INDEX_URL),--index-url $(TORCH_INDEX_URL))
	@# viz: rerun-sdk for `cpslam view` and the demo's demo.rrd (never used by the daemons);
	@# bags: rosbags for ROS bag and MCAP input.
	$(BIN)/python -m pip install -q -e ".[dev,viz,bags]"
	@touch $(STAMP)

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest $(PYTEST_ARGS)

test-fast: $(STAMP)
	$(BIN)/python -m pytest -m "not slow" $(PYTEST_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .

format: $(STAMP)
	$(BIN)/ruff format .

demo: $(STAMP)
	$(BIN)/cpslam demo --overwrite $(DEMO_ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache build *.egg-info
