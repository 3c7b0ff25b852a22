# Set-up and the main commands. `make demo` and `make test` create the virtual environment themselves.
SHELL := /bin/bash
VENV := .venv
BIN := $(VENV)/bin
export MUJOCO_GL ?= egl

.PHONY: install demo test test-docs lint bench system-deps clean

$(BIN)/.installed: pyproject.toml
	@PY="$$(scripts/find_python.sh)" && echo "Creating $(VENV) with $$PY" && "$$PY" -m venv $(VENV)
	$(BIN)/pip install --upgrade --quiet pip
	$(BIN)/pip install --quiet -e '.[test]'
	@touch $@

install: system-deps $(BIN)/.installed

# ffmpeg lets torchcodec decode videos; without it LeRobot falls back to PyAV (slower, long warnings).
system-deps:
	@command -v ffmpeg >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    (apt-get install -y -qq ffmpeg >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq ffmpeg >/dev/null)) \
	      || echo "note: could not install ffmpeg; LeRobot will decode videos with PyAV"; \
	  else echo "note: ffmpeg not found (apt-get install ffmpeg); LeRobot will decode videos with PyAV"; fi; }

demo: install
	$(BIN)/python examples/demo.py

test: install
	$(BIN)/pytest

# Every command block of docs/ as pasted, on tiny data (18 minutes on 2 cores; not part of `make test`).
test-docs: install
	LEROBOT_VIB_DOCS=1 $(BIN)/pytest tests/test_docs_commands.py

lint: install
	$(BIN)/ruff check src tests benchmarks examples scripts
	$(BIN)/ruff format --check src tests benchmarks examples scripts

bench: install
	$(BIN)/python benchmarks/bench_policy.py --output benchmarks/results/policy_$$(hostname).md

clean:
	rm -rf $(VENV) outputs
