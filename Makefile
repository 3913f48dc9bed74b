# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Headless MuJoCo rendering through OSMesa (Debian libosmesa6); render tests skip without it.
export MUJOCO_GL ?= osmesa
export PYOPENGL_PLATFORM ?= $(MUJOCO_GL)

.PHONY: install sysdeps demo test test-slow lint format bench paper clean

# Best effort: OSMesa for headless rendering, when we may install Debian packages.
sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q libOSMesa; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    (DEBIAN_FRONTEND=noninteractive apt-get install -y -q libosmesa6 >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null 2>&1 && \
	      DEBIAN_FRONTEND=noninteractive apt-get install -y -q libosmesa6 >/dev/null 2>&1)) || \
	    echo "note: libosmesa6 not installed; rendering tests will be skipped"; \
	  else echo "note: install libosmesa6 for headless rendering"; fi; \
	fi

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# The CPU build of torch that lies on this disk; a looser pin pulls a multi-GB CUDA build.
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[test,notebooks]'
	touch $(STAMP)

install: sysdeps $(STAMP)

demo: install
	$(BIN)/codesign demo

test: install
	$(BIN)/python -m pytest -m "not slow" -q

test-slow: install
	$(BIN)/python -m pytest -m slow -q

# ruff (style), import-linter (the layers of DESIGN.md, pyproject [tool.importlinter]),
# mypy (the lower layers, pyproject [tool.mypy]).
lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports
	$(BIN)/mypy

format: install
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

bench: install
	$(BIN)/codesign bench all

# Every table and figure of README's results (test seeds; resumes a partial results/paper),
# then docs/results, docs/figures and README's results block from it.
paper: install
	$(BIN)/codesign paper -o results/paper -j 2 --readme README.md

clean:
	rm -rf $(VENV) build *.egg-info
