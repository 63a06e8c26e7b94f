# Self-installing entry points: each target creates .venv if missing and installs the project first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PYTEST_ARGS ?=
WORKDIR ?= work/demo

.PHONY: install test test-all demo clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,onnx]'
	$(PY) -m pip install --quiet --no-deps 'jax2onnx>=0.17.1,<0.18'  # see pyproject's onnx extra
	@touch $(STAMP)

install: $(STAMP)

# The test command of the README (and of .ci/run). Slow checks are marked `slow` and skipped here.
# pytest exits 5 when it collects no test: that is not a failure; every other non-zero exit is.
test: $(STAMP)
	@$(PY) -m pytest -n 2 -m "not slow" $(PYTEST_ARGS); rc=$$?; \
	  if [ $$rc -eq 5 ]; then echo "no tests collected"; exit 0; fi; exit $$rc

# Everything, slow checks included.
test-all: $(STAMP)
	$(PY) -m pytest -n 2 $(PYTEST_ARGS)

# The main job: train the demo model on the built-in synthetic stereo video, then evaluate it.
demo: $(STAMP)
	$(PY) -m bridge_jax.demo --workdir=$(WORKDIR)

clean:
	rm -rf $(VENV) .pytest_cache
