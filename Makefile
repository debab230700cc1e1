# The two README commands:  `make demo`  and  `make test`.
# Both build the environment first (idempotent), so a fresh clone needs nothing else.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-all bench addon clean

$(STAMP): pyproject.toml constraints.txt scripts/setup.sh
	bash scripts/setup.sh $(PY) $(VENV)
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/mpib demo --out out/demo
	$(BIN)/mpib bench --out out/bench

test: $(STAMP)
	$(BIN)/python -m pytest -m "not slow" -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/mpib bench --out out/bench

addon: $(STAMP)
	$(BIN)/python scripts/build_addon.py --out dist

clean:
	rm -rf $(VENV) out dist blender_addon/wheels
