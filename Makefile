# Two commands on a fresh machine with Python 3.11 and make:  `make run`  and  `make test`.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# What a run needs (make run); the full set (tests, lint, docs, benchmarks, Docker SDK) goes on top of it.
RUN_STAMP := $(VENV)/.installed-run
# Four test processes on two cores (pytest-xdist): much of the suite's time waits on brokers and timeouts (at
# -n 2 it used 1.2 cores; pytest 12 min 14 s there, 10 min 31 s at -n 3, 2026-12-03; on 2026-12-06's VM 11 min 9 s
# to 11 min 16 s at -n 3 and 10 min 11 s at -n 4, 1149 tests). Tests that share the end-to-end runs keep together
# (xdist_group "e2e"). PYTEST_JOBS= runs them in one process.
PYTEST_JOBS ?= -n 4 --dist loadgroup
PIP    := $(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt
MKVENV := test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
RUN_EXTRAS := learn,broker,tb
ALL_EXTRAS := $(RUN_EXTRAS),dev,deploy,video,bench,docs

.PHONY: run test test-fast lint venv bench bench-quick soak clean help test-docker docker-dev docs docs-build tensorboard \
	k8s-check swarm-test scale scale-quick

help:
	@echo "make run    - federation on this machine: embedded broker + chief + FEDRL_WORKERS workers (default 4)"
	@echo "make test   - lint, the docs built strict, then the whole test suite (creates the virtual environment first)"
	@echo "make test-fast - lint, then the tests not marked slow (end-to-end training runs) or docker: the inner loop"
	@echo "make lint   - ruff, mypy over every package, and the package layering (lint-imports, pyproject.toml)"
	@echo "make bench  - the paper's experiment (python -m bench.paper): every task and strategy, 10 seeds, references, cost;"
	@echo "              JSON + figures into bench/results/, docs/results.md and README table (hours on 2 cores)"
	@echo "make bench-quick - its reduced variant into bench/results/quick/ (under 15 min on 2 cores)"
	@echo "make docs   - serve the documentation site on http://127.0.0.1:8000/ (mkdocs serve; Ctrl-C stops it)"
	@echo "make docs-build - build it into site/ with warnings as errors (mkdocs build --strict)"
	@echo "make tensorboard RUN=runs/<run> - install the TensorBoard viewer (the viewer extra) and serve the run's event files"
	@echo "make soak   - 16 workers over Mosquitto to the end, memory and round latency watched (bench/results/soak.*)"
	@echo "make scale  - flat chief against a root fed by edge chiefs, 4 to 1,024 simulated devices (bench/results/scale.json)"
	@echo "make scale-quick - its reduced set: flat up to 64 devices, 256 devices over 4 edges"
	@echo "make test-docker - containerised end-to-end tests (docker compose up, python -m deploy.docker)"
	@echo "make docker-dev  - (root) Docker engine + local base/Mosquitto images where no registry is reachable"
	@echo "make k8s-check   - render the Kubernetes manifests (kubectl kustomize) and validate them against 1.32"
	@echo "make swarm-test  - the multi-site stack on a single-node Docker Swarm (swarm init if needed; docs/how-to/sites.md)"

venv: $(STAMP)

$(RUN_STAMP): pyproject.toml constraints.txt
	$(MKVENV)
	$(PIP) -e ".[$(RUN_EXTRAS)]"
	touch $(RUN_STAMP)

# The full set includes the run's: one install (one resolution) for both stamps.
$(STAMP): pyproject.toml constraints.txt
	$(MKVENV)
	$(PIP) -e ".[$(ALL_EXTRAS)]"
	touch $(RUN_STAMP) $(STAMP)

run: $(RUN_STAMP)
	$(BIN)/python -m deploy.run_local

# The TensorBoard viewer is not part of a run (the chief writes the event files with tensorboardX).
tensorboard: $(RUN_STAMP)
	@test -n "$(RUN)" || { echo "usage: make tensorboard RUN=runs/<run>"; exit 2; }
	$(PIP) -e ".[viewer]"
	$(BIN)/tensorboard --logdir "$(RUN)/tensorboard" --host 127.0.0.1

test: lint
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict --quiet
	$(BIN)/python -m pytest -q $(PYTEST_JOBS)

test-fast: lint
	$(BIN)/python -m pytest -q $(PYTEST_JOBS) -m "not slow and not docker"

lint: $(STAMP)
	$(BIN)/python -m ruff check .
	$(BIN)/python -m mypy
	$(BIN)/lint-imports

bench: $(STAMP)
	$(BIN)/python -m bench.paper

bench-quick: $(STAMP)
	$(BIN)/python -m bench.paper --quick

soak: $(STAMP)
	$(BIN)/python -m bench.soak

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache site

# The documentation site (mkdocs.yml, docs/): served with live reload, or built with warnings as errors.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs serve -a 127.0.0.1:8000

docs-build: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict

# Containerised end-to-end tests: compose up + python -m deploy.docker, 2-worker CartPole (needs Docker + Compose).
test-docker: $(STAMP)
	FEDRL_REQUIRE_DOCKER=1 $(BIN)/python -m pytest -m docker -q -s

# The multi-site deployment on orchestrators (docs/how-to/sites.md). k8s-check renders deploy/k8s/example offline
# with its secrets from deploy.sites and validates every object against the Kubernetes 1.32 schemas (also in make
# test when kubectl is installed). swarm-test makes this engine a single-node swarm if it is none yet, then deploys
# deploy/swarm/stack.yml (two sites, a broker each, the core, the chief) and runs a federation to its end.
scale: $(STAMP)
	$(BIN)/python -m bench.scale

scale-quick: $(STAMP)
	$(BIN)/python -m bench.scale --quick --out bench/results/scale-quick.json

k8s-check: $(STAMP)
	$(BIN)/python -m pytest -q tests/deploy/test_k8s.py

swarm-test: $(STAMP)
	@test "$$(docker info --format '{{.Swarm.LocalNodeState}}' 2>/dev/null)" = active \
		|| docker swarm init --advertise-addr 127.0.0.1
	FEDRL_REQUIRE_DOCKER=1 $(BIN)/python -m pytest -m docker -q -s tests/deploy/test_swarm.py

# Machines without registry access (root): engine, local base/Mosquitto images, CPU torch wheel (deploy/dev/).
docker-dev:
	deploy/dev/prepare.sh
