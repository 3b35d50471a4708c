# Two commands on a fresh machine: `make demo` and `make test`. Both install first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PLUGIN := policies/lerobot_policy_hiveformer
DEMO_RAW := data/raw/push_buttons

.PHONY: install demo test bench clean

install: $(STAMP)

# Re-installs only when a distribution's declaration changes.
$(STAMP): pyproject.toml $(PLUGIN)/pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]" -e $(PLUGIN)
	touch $(STAMP)

# The main job on a small default: expert episodes of both splits → MCAP → inspect one.
demo: install
	$(BIN)/demo-factory tasks
	$(BIN)/demo-factory generate --task push_buttons --split train --episodes 6 --out $(DEMO_RAW)
	$(BIN)/demo-factory generate --task push_buttons --split test --episodes 4 --out $(DEMO_RAW)
	$(BIN)/demo-factory inspect $$(ls $(DEMO_RAW)/*.mcap | head -n 1)

test: install
	$(BIN)/python -m pytest

bench: install
	$(BIN)/python -m demo_factory.bench --out bench/results.json

clean:
	rm -rf $(VENV) data outputs
