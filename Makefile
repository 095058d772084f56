# Entry points: `make demo`, `make test`, `make bench` (see README.md).

SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
BENCH_STAMP := $(VENV)/.bench-installed

# Keep any ROS traffic from tests, demo and benchmarks on this host.
ROS_DOMAIN_ID ?= 42
# One BLAS thread per process (jointfit_core sets it too, unless numpy was imported first, as pytest
# may): the test workers and live nodes share 2 cores (bench/results/blas_threads.md).
ROS_ENV := ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=$(ROS_DOMAIN_ID) OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1

.PHONY: venv lint test attack demo demo-offline bench soak clean

venv: $(STAMP)

$(STAMP): requirements.txt setup.py setup.cfg pyproject.toml
	rm -f $(STAMP)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -r requirements.txt
	$(BIN)/python -m pip install -q --no-deps --no-build-isolation -e .
	touch $(STAMP)

lint: venv
	$(BIN)/ruff check jointfit_core jointfit_ros test bench
	$(BIN)/mypy jointfit_core jointfit_ros

# Two passes: the tests that start no live node on both cores (one worker per file: each file's ROS
# domains stay in one process), then the live-node tests (`ros` marker) alone, with the machine to
# themselves as a lab's node would have it.
test: venv lint
	$(ROS_ENV) $(BIN)/python -m pytest -m "not ros and not attack" -n 2 --dist loadfile
	$(ROS_ENV) $(BIN)/python -m pytest -m "ros and not attack"

# Long adversarial runs against a live node (e.g. hypothesis over every parameter), not part of make test.
attack: venv
	$(ROS_ENV) $(BIN)/python -m pytest -m attack

demo: venv
	$(ROS_ENV) $(BIN)/python -m jointfit_ros.demo
	$(ROS_ENV) $(BIN)/python -m jointfit_core.demo

demo-offline: venv
	$(ROS_ENV) $(BIN)/python -m jointfit_core.demo

# The peer comparison's optional extras (biobuddy: SCoRE/SARA) go into the same .venv,
# only for the benchmarks; the package never imports them.
$(BENCH_STAMP): $(STAMP) requirements-bench.txt
	$(BIN)/python -m pip install -q -r requirements-bench.txt
	touch $(BENCH_STAMP)

bench: venv $(BENCH_STAMP)
	shopt -s nullglob; \
	for f in bench/*.py; do \
		case "$$(basename "$$f")" in _*|soak.py) continue ;; esac; \
		echo "== $$f"; \
		$(ROS_ENV) $(BIN)/python "$$f" || exit 1; \
	done

# An hour of 500 Hz data through the node in accelerated time (~20-30 min): bench/results/soak.md.
soak: venv
	$(ROS_ENV) $(BIN)/python bench/soak.py

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache .hypothesis build *.egg-info
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
