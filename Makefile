# GeoPose: set-up, demo and tests. Everything installs into .venv/ in this folder.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup demo test test-slow bench clean

$(BIN)/geopose: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $@

setup: $(BIN)/geopose

demo: setup
	$(BIN)/geopose demo --out demo_out

test: setup
	$(BIN)/python -m pytest -q

test-slow: setup
	GEOPOSE_SLOW=1 $(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) demo_out
