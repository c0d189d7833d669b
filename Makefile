# armfit — set-up, demo and tests. `make demo` and `make test` are all a new machine needs.
#
# The virtual environment .venv gets the locked, tested versions of requirements.lock;
# `make lock` regenerates that file from a clean environment, the dask, control and hdf5 extras included
# (see the README's developer section). `make test-latest` and `make test-oldest` run the
# suite against the newest versions pyproject.toml allows and against its lower bounds,
# each in its own venv.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
PIP    := python -m pip install --quiet --disable-pip-version-check

.PHONY: demo test test-slow lint bench clean lock test-latest test-oldest compile

$(STAMP): pyproject.toml requirements.lock
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/$(PIP) -r requirements.lock
	$(BIN)/$(PIP) --no-deps -e .
	touch $(STAMP)

# armfit's own bytecode, as a regular install writes it (an editable install does not, and
# compiling the package at every start would add about half a second to each command)
compile: $(STAMP)
	$(BIN)/python -m compileall -q armfit

demo: $(STAMP) compile
	$(BIN)/armfit run sample_data/study -o out/study --overwrite --jobs 2
	$(BIN)/armfit run sample_data/hidden -o out/hidden --overwrite --jobs 2

# the suite's test files are shared out between TEST_JOBS processes (pytest-xdist), whole
# files at a time, so that a module's fixtures are made once
TEST_JOBS ?= 2
XDIST     := -n $(TEST_JOBS) --dist loadfile

test: $(STAMP)
	$(BIN)/python -m pytest -q $(XDIST)

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow $(XDIST)

lint: $(STAMP)
	$(BIN)/ruff check armfit tests benchmarks

# every script with its defaults, then the run of a study with a hidden delay against the
# same study without it
bench: $(STAMP) compile
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done
	$(BIN)/python benchmarks/bench_run.py --effect delay=0.012 --against-null --repeat 5

# Regenerate requirements.lock: newest versions pyproject.toml allows, resolved by pip in
# a clean venv, frozen with exact versions. Run `make test` (and commit) afterwards.
lock:
	rm -rf .venv-lock && $(PYTHON) -m venv .venv-lock
	.venv-lock/bin/$(PIP) '.[dev,dask,control,hdf5]'
	{ echo "# Exact versions the test suite is green with. Regenerate: make lock"; \
	  .venv-lock/bin/python -m pip freeze --exclude armfit; } > requirements.lock
	rm -rf .venv-lock

# The newest versions pyproject.toml allows (no lock), the dask, control and hdf5 extras included.
test-latest:
	rm -rf .venv-latest && $(PYTHON) -m venv .venv-latest
	.venv-latest/bin/$(PIP) --upgrade -e '.[dev,dask,control,hdf5]'
	.venv-latest/bin/python -m pip freeze --exclude armfit
	.venv-latest/bin/python -m pytest -q -p no:cacheprovider $(XDIST)

# The lower bounds of pyproject.toml (every `name>=X` installed as `name==X`).
test-oldest:
	rm -rf .venv-oldest && $(PYTHON) -m venv .venv-oldest
	$(PYTHON) .ci/lower-bounds.py pyproject.toml > .venv-oldest/constraints.txt
	.venv-oldest/bin/$(PIP) -c .venv-oldest/constraints.txt -e '.[dev]'
	.venv-oldest/bin/python -m pip freeze --exclude armfit
	.venv-oldest/bin/python -m pytest -q -p no:cacheprovider $(XDIST)

clean:
	rm -rf out build *.egg-info .pytest_cache .venv-lock .venv-latest .venv-oldest
