# Set-up and everyday commands. Each target installs what it needs into .venv first,
# so `make run` and `make test` work on a fresh clone.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin

.PHONY: run test install dev bench lint clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# A regular (non-editable) install: the tests exercise the package as users get it.
install: $(BIN)/python
	$(BIN)/pip install -q '.[test]'

# Editable install for working on the code (rebuild the native module with `make dev`).
dev: $(BIN)/python
	$(BIN)/pip install -q scikit-build-core pybind11
	$(BIN)/pip install -q --no-build-isolation -e '.[test,bench]'

# Builds the demo into the out-of-core format, then renders the built model.
run: install
	@mkdir -p out
	$(BIN)/vastray build demo -o out/demo.vast --force
	$(BIN)/vastray inspect out/demo.vast
	$(BIN)/vastray render out/demo.vast --shading sun -o out/demo.png

lint: install
	$(BIN)/ruff check .

test: lint
	$(BIN)/pytest

bench: $(BIN)/python
	$(BIN)/pip install -q '.[bench]'
	$(BIN)/python bench/rays.py
	$(BIN)/python bench/build.py

clean:
	rm -rf build out .pytest_cache .ruff_cache
