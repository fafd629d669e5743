# Two commands do everything (see README):
#   make run    -> installs into .venv and runs the main job on its built-in default
#   make test   -> installs into .venv (with test extras) and runs the test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
OUT    ?= results

.PHONY: run test bench install install-tests clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-tests: $(VENV)/.installed pyproject.toml
	$(PY) -m pip install --quiet -e ".[tests]"
	touch $@

install: $(VENV)/.installed
install-tests: $(VENV)/.installed-tests

run: $(VENV)/.installed
	$(VENV)/bin/python -m tuning --out $(OUT)

test: $(VENV)/.installed-tests
	$(PY) -m pytest -n 2 -q

bench: $(VENV)/.installed-tests
	$(PY) benchmarks/bench_simulate.py

clean:
	rm -rf $(VENV) results .pytest_cache
