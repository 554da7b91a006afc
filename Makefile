# `make demo` and `make test` install everything they need into .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

CHROMIUM := /usr/bin/chromium
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: demo test test-fast lint install clean rebuild-pusht-64 rebuild-pilesweep-64

# torch is pinned and installed first: an unpinned torch would pull the CUDA build.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	MUJOCO_GL=egl $(VENV)/bin/iwsim demo

# The browser tests drive Debian's chromium through Playwright (no browser download).
$(CHROMIUM):
	$(SUDO) apt-get update -q
	DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q chromium

# Everything: unit tests, end-to-end runs, the browser and the two-process DDP tests. Two
# workers (pytest-xdist), a file's tests on one of them, each on one torch thread: two
# threads per worker would oversubscribe two cores.
XDIST := -n 2 --dist loadfile --no-loadscope-reorder --durations=25
test: $(STAMP) $(CHROMIUM)
	MUJOCO_GL=egl OMP_NUM_THREADS=1 $(PY) -m pytest -q $(XDIST)

# The inner loop: without the tests marked slow, browser or ddp (pyproject.toml).
test-fast: $(STAMP)
	MUJOCO_GL=egl OMP_NUM_THREADS=1 $(PY) -m pytest -q $(XDIST) -m "not slow and not browser and not ddp"

# The shipped world model's whole recipe (about 7.2 core-hours), resumable across sessions:
# rerun it after an interruption. It ends with the rebuilt model's yardstick row.
rebuild-pusht-64: $(STAMP)
	IWSIM=$(VENV)/bin/iwsim PYTHON=$(PY) bash checkpoints/pusht-64/recipe.sh

# The shipped pile-sweeping world model's whole recipe (about 7.5 core-hours), resumable the same way.
rebuild-pilesweep-64: $(STAMP)
	IWSIM=$(VENV)/bin/iwsim PYTHON=$(PY) bash checkpoints/pilesweep-64/recipe.sh

lint: $(STAMP)
	$(PY) -m ruff check src tests bench scripts
	$(PY) -m mypy

clean:
	rm -rf $(VENV) outputs
