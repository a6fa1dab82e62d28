# The two commands of the README:
#   make train   set up .venv and run the demo: PEBBLE learns cheetah_run from an oracle's labels,
#                3 seeds, about 3 minutes on 2 CPU cores, the venv included (174 s, docs/training.md;
#                the `demo` preset of config.py; tests/test_demo.py)
#   make test    set up .venv with the test extras and run ruff + the test suite
#                (first installing Debian's chromium, chromium-driver and Mesa's EGL where they
#                are missing and apt-get can run as root: the labelling page's browser test and
#                MuJoCo's clips need them)
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
METHOD ?=
ARGS ?=
PYTEST_ARGS ?=

# Debian packages the tests need and `make test` installs when missing (as root, with apt-get): Chromium
# for the labelling page's browser test (Playwright drives /usr/bin/chromium; it cannot download its own
# browser here) and Mesa's software EGL for MuJoCo's renderer (the human teacher's clips and the
# fidelity test of the pure-JAX camera, MUJOCO_GL=egl). Where that is impossible those tests skip and say why.
SYSTEM_PACKAGES ?= chromium chromium-driver libegl1 libegl-mesa0 libgl1-mesa-dri

.PHONY: train test test-heavy lint clean system-deps

$(VENV)/.base: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e .
	touch $@

$(VENV)/.test: $(VENV)/.base
	$(PY) -m pip install -q -e '.[test]'
	touch $@

# warp-lang (--impl warp) for make test-heavy's tests of MuJoCo Warp's step: importing it costs every process that
# imports mujoco.mjx about 3 s, which make test leaves out.
$(VENV)/.warp: $(VENV)/.base
	$(PY) -m pip install -q -e '.[warp]'
	touch $@

train: $(VENV)/.base
	$(PY) -m rebel_jax.train $(METHOD) --preset demo --seeds 3 $(ARGS)

lint: $(VENV)/.test
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

system-deps:
	@missing=""; for p in $(SYSTEM_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing$$missing (apt-get)"; \
	    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; } || \
	      echo "note: apt-get could not install$$missing; the tests that need them are skipped"; \
	  else \
	    echo "note: missing Debian packages:$$missing (sudo apt-get install$$missing); the tests that need them are skipped"; \
	  fi; \
	fi

test: lint system-deps
	$(PY) -m pytest -q -n 2 --dist loadgroup -m "not heavy" $(PYTEST_ARGS)

# What `make test` leaves out (pytest marker `heavy`) to stay within 10 minutes on 2 cores: the minutes-long
# end-to-end runs (the command `make train` runs, checked to learn; SAC on walker_stand; the pixel PEBBLE,
# REBEL and SURF runs; the 2-process --distributed runs; MuJoCo Warp's step, with warp-lang installed) and checks
# whose every compile is another 10-40 s
# while make test covers the same code another way (each test says how: grep "mark.heavy" tests/).
# Run it before changing the physics, the trainer's round or the pixel agents.
test-heavy: $(VENV)/.test $(VENV)/.warp
	$(PY) -m pytest -q -n 2 --dist loadgroup -m heavy $(PYTEST_ARGS)

# The checkout's own files only: the tests' compilation cache (.jax_cache) and the runs. The training command's
# per-user compilation cache (~/.cache/rebel_jax/jax, docs/training.md) is outside the repo and left alone.
clean:
	rm -rf $(VENV) .jax_cache runs
