# Three commands do everything (see README):
#   make run    -> installs into .venv and runs the main job, the gain tuner (python -m
#                  tuning), on its built-in default into results/ (OUT=DIR elsewhere)
#   make test   -> installs into .venv (with test and docs extras) and runs the test suite
#   make docs   -> builds the documentation site into site/ (executes the notebooks)
# Each installs the tested versions pinned in constraints.txt (pyproject.toml keeps the
# compatible ranges); `make lock` re-resolves the newest versions and rewrites the file.
# Also: `make bench` and `make stress` (benchmarks/), `make clean`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
OUT    ?= results
PIP    := $(PY) -m pip install --quiet -c constraints.txt

.PHONY: run test docs bench stress install install-tests lock clean

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PIP) -e .
	touch $@

$(VENV)/.installed-tests: $(VENV)/.installed pyproject.toml constraints.txt
	$(PIP) -e ".[tests,docs]"
	touch $@

install: $(VENV)/.installed
install-tests: $(VENV)/.installed-tests

run: $(VENV)/.installed
	$(VENV)/bin/python -m tuning --out $(OUT)

test: $(VENV)/.installed-tests
	$(PY) -m pytest -n 2 -q

# The documentation site (mkdocs.yml) into site/, strict (a broken link or reference
# fails), executing every notebook; PMSMJAX_DOCS_EXECUTE=false renders them unexecuted.
docs: $(VENV)/.installed-tests
	$(VENV)/bin/mkdocs build --strict

bench: $(VENV)/.installed-tests
	$(PY) -m benchmarks.throughput.simulate --json $(OUT)/benchmarks/throughput.simulate.json

stress: $(VENV)/.installed-tests
	$(PY) -m benchmarks.reproducers.stress_hang --out $(OUT)/stress --json $(OUT)/stress/stress.json

# Resolve the newest versions allowed by pyproject.toml in a scratch environment, run
# nothing, and write them to constraints.txt (review the diff, then run `make test`).
lock:
	rm -rf .lock-venv
	$(PYTHON) -m venv .lock-venv
	.lock-venv/bin/python -m pip install --quiet --upgrade pip
	.lock-venv/bin/python -m pip install --quiet -e ".[tests,docs,notebooks]"
	{ echo "# Tested versions of every dependency (make lock rewrites this file)."; \
	  .lock-venv/bin/python -m pip freeze --exclude-editable | LC_ALL=C sort -f; } > constraints.txt
	rm -rf .lock-venv
	@echo "constraints.txt updated: review the diff, then run make test"

clean:
	rm -rf $(VENV) .lock-venv results .pytest_cache site
