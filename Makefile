# Two entry points (see README): `make demo` and `make test`.
# Each creates .venv on first use and installs the package with its test extra.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
OUT    ?= out/demo
PYTEST_ARGS ?= -n 2

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -e ".[test]"
	touch $@

.PHONY: install demo test bench lint
install: $(VENV)/.installed

demo: $(VENV)/.installed
	$(VENV)/bin/ppr demo --out $(OUT)

test: $(VENV)/.installed
	$(PY) -m pytest $(PYTEST_ARGS)

bench: $(VENV)/.installed
	for f in bench/bench_*.py; do $(PY) $$f || exit 1; done

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
