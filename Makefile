# The two commands of the README:
#   make train   set up .venv and train on the small default (CPU, a few minutes)
#   make test    set up .venv with the test extras and run ruff + the test suite
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
ARGS ?=
PYTEST_ARGS ?=

.PHONY: train test lint gl clean

# MuJoCo's own renderer, for the fidelity test of the pure-JAX camera (tests/test_render.py),
# through Mesa's software EGL (MUJOCO_GL=egl). Installed with apt-get when missing; where that
# is impossible (not root, not Debian) the test is skipped and says why.
GL_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri

$(VENV)/.base: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e .
	touch $@

$(VENV)/.test: $(VENV)/.base
	$(PY) -m pip install -q -e '.[test]'
	touch $@

train: $(VENV)/.base
	$(PY) -m rebel_jax.train --preset tiny --algo rebel --rebel.lam -0.01 $(ARGS)

lint: $(VENV)/.test
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

gl:
	@dpkg -s $(GL_PACKAGES) >/dev/null 2>&1 || \
	  { apt-get update -qq && apt-get install -y -qq --no-install-recommends $(GL_PACKAGES); } || \
	  echo "make gl: could not install $(GL_PACKAGES); tests/test_render.py skips its MuJoCo-renderer comparison"

test: lint gl
	$(PY) -m pytest -q -n 2 --dist loadgroup $(PYTEST_ARGS)

clean:
	rm -rf $(VENV) .jax_cache runs
