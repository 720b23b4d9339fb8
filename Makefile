# USER — two commands on a fresh machine: `make demo` and `make test`.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PROTOS := $(wildcard proto/user/v1/*.proto)
STUBS := user/v1/.generated
# python3.12: on PATH, else pyenv's, else the system's. Each candidate is run, not just found
# (a pyenv shim exists even when 3.12 is not selected).
FIND_PY312 := for c in python3.12 $$HOME/.pyenv/versions/3.12*/bin/python3.12 /usr/local/bin/python3.12 /usr/bin/python3.12; do \
	if "$$c" -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null; then echo "$$c"; break; fi; done

.PHONY: install proto demo test test-fast lint bench load clean help fuzz compose-test gpu

help:
	@echo "make demo   install + train two embodiments at once (2 sim arms reach, a Panda picks) through the five services"
	@echo "make test   install + run the test suite"
	@echo "make fuzz   long property-based run over every RPC (10k examples per test)"
	@echo "make load   64 simulated robots at 10 Hz for 10 min against one local stack (LOAD_ARGS=\"--duration 30 --edges 8\")"
	@echo "make compose-test  build the image, run docker-compose.yml, kill replay and learner, check, tear down"
	@echo "make gpu    on a CUDA machine: the CUDA tests and the GPU timings (learner, flow_vla, inference service)"
	@echo "make proto | lint | bench | clean"

$(STAMP): pyproject.toml constraints.txt
	@py=$$($(FIND_PY312)); if [ -z "$$py" ]; then echo "Python 3.12 not found (python3.12 or pyenv 3.12.x)"; exit 1; fi; \
	echo "using $$py"; [ -x $(PY) ] || "$$py" -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
	set -o pipefail; $(PY) -m pip install -q -c constraints.txt -e ".[dev]" 2>&1 | { grep -v "^WARNING: Location" || true; }
	touch $(STAMP)

install: $(STAMP) $(STUBS)

# Generated code is never edited by hand: proto/ is the source of truth.
$(STUBS): $(PROTOS) $(STAMP)
	rm -rf user/v1 && mkdir -p user/v1
	$(PY) -m grpc_tools.protoc -Iproto --python_out=. --pyi_out=. --grpc_python_out=. $(PROTOS)
	touch user/v1/__init__.py $(STUBS)

proto: $(STAMP)
	rm -f $(STUBS) && $(MAKE) --no-print-directory $(STUBS)

demo: install
	MUJOCO_GL=egl $(VENV)/bin/userctl up --config configs/demo.yaml --fresh

test: install
	MUJOCO_GL=egl $(PY) -m pytest -q -rs --durations=10

test-fast: install
	MUJOCO_GL=egl $(PY) -m pytest -q -m "not slow"

# Long property-based run: >= 10k messages per RPC group of every service (the normal run does 40).
fuzz: install
	USER_FUZZ_EXAMPLES=10000 MUJOCO_GL=egl $(PY) -m pytest -q -s tests/test_fuzz.py

# Not part of `make test`: needs a docker engine and builds a 6 GB image (docs/notes/ops.md). Uses the local
# Debian bases from deploy/docker/build-base.sh when they exist (no public registry needed).
compose-test: install
	$(PY) deploy/compose_test.py

# On a machine with a CUDA GPU: the CUDA tests (skipped elsewhere, as in CI) and the GPU timings.
gpu: install
	$(PY) -m pytest -q -rs tests/test_cuda.py
	USER_INFERENCE_VLA_PROFILES=vla $(PY) -m bench --only gpu,inference_vla --set inference.device=cuda \
		--json runs/bench/gpu.json --markdown runs/bench/gpu.md

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

bench: install
	MUJOCO_GL=egl $(PY) -m bench

# Not part of `make bench`: it holds one stack under load for the whole --duration (600 s by default).
load: install
	MUJOCO_GL=egl $(PY) -m bench --only load $(LOAD_ARGS)

clean:
	rm -rf user/v1 .pytest_cache .ruff_cache
