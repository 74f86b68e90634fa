# The two set-up commands of README.md. Each builds its own virtualenv from scratch.
PYTHON ?= python3
VENV := .venv
SERVE_VENV := .venv-serve
PIP := --disable-pip-version-check --no-input -q
# Loopback unless asked: HOST=0.0.0.0 serves the farm (the Docker image binds 0.0.0.0 itself).
HOST ?= 127.0.0.1
PORT ?= 8000
# Serving, training and the tests need the C++ op library, which a plain `pip install .` (the
# client's install) does not build (pyproject.toml, [tool.scikit-build]).
WITH_OPS := QUIETFRAME_BUILD_OPS=1

CYCLES_VENV := .venv-cycles
CYCLES_PYTHON ?= python3.11

.PHONY: test serve lint bench clean cycles blender-addon

# A virtualenv with a current pip: $(call new-venv,PYTHON,DIR)
new-venv = $(1) -m venv $(2) && $(2)/bin/python -m pip install $(PIP) --upgrade pip

# torch first and pinned: 2.13.0 is the CPU build; anything else pulls several GB of CUDA wheels.
$(VENV)/.base:
	$(call new-venv,$(PYTHON),$(VENV))
	$(VENV)/bin/python -m pip install $(PIP) torch==2.13.0
	touch $@

# Installs the package itself (not editable: tests run what a user installs, C++ ops included).
install-dev: $(VENV)/.base
	$(WITH_OPS) $(VENV)/bin/python -m pip install $(PIP) ".[train,serve,client,dev]"

# Two workers (pytest-xdist) that steal work from each other: a serial run took 9.5 min on the
# 2-core CI machine (many tests wait on sockets and subprocesses) and the suite must stay under
# 6 min; with a render sharing the cores, whole files per worker took 6:28, work stealing 5:58.
test: install-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/python -m pytest tests -n 2 --dist worksteal --durations=15

$(SERVE_VENV)/.base:
	$(call new-venv,$(PYTHON),$(SERVE_VENV))
	touch $@

# What the wheel is built from (pyproject's wheel.packages, the op sources, the readme): the
# serve venv is reinstalled only when one of these changed, so an unchanged start takes seconds.
# A deleted file is not seen: `rm $(SERVE_VENV)/.installed` forces a reinstall.
PACKAGE_SOURCES := pyproject.toml README.md $(shell find model scenes export runtime service \
	client wire bench experiments models -path models/training -prune -o -name __pycache__ -prune \
	-o -type f ! -name '*.pyc' -print)

$(SERVE_VENV)/.installed: $(SERVE_VENV)/.base $(PACKAGE_SOURCES)
	$(WITH_OPS) $(SERVE_VENV)/bin/python -m pip install $(PIP) ".[serve,client]"
	touch $@

serve: $(SERVE_VENV)/.installed
	$(SERVE_VENV)/bin/quietframe serve --host $(HOST) --port $(PORT)

# Blender Cycles (bpy 4.5, Python 3.11) in a venv of its own: the Cycles renders and the tests
# that run Blender (tests/cycles_support.py finds it; skipped without it). CI installs it.
$(CYCLES_VENV)/.base:
	$(call new-venv,$(CYCLES_PYTHON),$(CYCLES_VENV))
	touch $@

cycles: $(CYCLES_VENV)/.base
	$(CYCLES_VENV)/bin/python -m pip install $(PIP) ".[cycles]"

# The Blender extension: build/quietframe-blender-<version>.zip, the add-on in blender/ with a
# copy of wire/ inside (docs/blender-addon.md). Standard library only: any python3 builds it.
blender-addon:
	$(PYTHON) blender/build_extension.py

lint: install-dev
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) $(SERVE_VENV) $(CYCLES_VENV) build

# Development: make the source folders importable as quietframe.<folder> in .venv without a
# rebuild per edit (symlinks mimic the wheel layout). Point QUIETFRAME_OPS_LIBRARY at a build of
# export/ops (cmake -S export/ops -B build/ops && cmake --build build/ops).
dev: $(VENV)/.base
	$(VENV)/bin/python tools/dev_links.py
