# The two front-door commands: each creates .venv and installs what it needs.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed

.PHONY: demo test test-all bench bench-quick clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e ".[plot,interop,progress,speed,bench,test]"
	-$(BIN)/python -m pip install -q slycot
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python examples/lugre_demo.py --no-show

test: $(STAMP)
	$(BIN)/python -m pytest -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m ""

bench: $(STAMP)
	$(BIN)/python -m pip install -q -e ".[bench,speed]"
	$(BIN)/python benchmarks/run_all.py

bench-quick: $(STAMP)
	$(BIN)/python -m pip install -q -e ".[bench,speed]"
	$(BIN)/python benchmarks/run_all.py --quick

clean:
	rm -rf $(VENV) out build src/*.egg-info .pytest_cache
