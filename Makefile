# fishsim: the README's two commands (`make demo`, `make test`) set everything up themselves.
# TORCH picks the torch build installed first (default: the CPU build; e.g. `make install
# TORCH="torch==2.13.0 --index-url https://download.pytorch.org/whl/cu126"` for a GPU).

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
TORCH  ?= torch==2.13.0
STAMP  := $(VENV)/.fishsim-installed
DEMO   ?= outputs/demo
export OMP_NUM_THREADS ?= 2

.PHONY: install demo test test-fast bench lint clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(TORCH)
	PYTHONWARNINGS=ignore $(BIN)/python -m pip install -q -e '.[dev]'   # no setuptools editable-install notice
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/fishsim mesh out_dir=$(DEMO)
	$(BIN)/fishsim simulate out_dir=$(DEMO) overwrite=true
	$(BIN)/fishsim render $(DEMO)/trajectory.h5 out_dir=$(DEMO)/render pngs=false
	@echo "demo outputs are in $(DEMO)/"

test: install
	$(BIN)/python -m pytest -q -n 2

test-fast: install
	$(BIN)/python -m pytest -q -m "not slow"

bench: install
	$(BIN)/python -m benchmarks.run

lint: install
	$(BIN)/ruff check fishsim tests benchmarks

clean:
	rm -rf $(VENV) outputs .pytest_cache
