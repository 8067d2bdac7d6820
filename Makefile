# Both targets do all set-up on a fresh machine that has only python3.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin

.PHONY: demo test lint bench fuzz docs site clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[test]'
	touch $@ $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/deployer demo

test: $(VENV)/.installed-test
	$(BIN)/python -m pytest -q
	$(BIN)/ruff check deployer tests benchmarks ansible_collections
	$(BIN)/mypy deployer tests
	$(BIN)/mkdocs build --strict --site-dir build/site   # the manual: a broken link between pages fails

lint: $(VENV)/.installed-test
	$(BIN)/ruff check deployer tests benchmarks ansible_collections
	$(BIN)/mypy deployer tests

docs: $(VENV)/.installed
	$(BIN)/deployer docs --out docs/reference

site: $(VENV)/.installed-test
	$(BIN)/mkdocs build --strict --site-dir build/site

bench: $(VENV)/.installed
	$(BIN)/python -m benchmarks.run

fuzz: $(VENV)/.installed-test
	$(BIN)/python -m tests.fuzz --files 200000 --seconds 900

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build *.egg-info
