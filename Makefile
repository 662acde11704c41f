# Every target creates .venv and installs the project by itself (torch's CPU wheel first).
VENV := .venv
PY := $(VENV)/bin/python
QUICK ?=

.PHONY: install test reproduce bench lint clean

$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -e ".[test]"
	touch $@

install: $(VENV)/.installed

test: install
	$(PY) -m ruff check dcsc_torchrl envs recipes tests bench
	$(PY) -m pytest -q

reproduce: install
	$(VENV)/bin/dcsc reproduce $(if $(QUICK),--quick,)

bench: install
	$(PY) -m pip install -e ".[bench]"
	for b in bench/bench_*.py; do $(PY) $$b || exit 1; done
	$(PY) bench/bench_pretrain.py --task uav --frames 8000  # DDPG against SB3 (the loop above ran A2C)

lint: install
	$(PY) -m ruff check dcsc_torchrl envs recipes tests bench

clean:
	rm -rf $(VENV) results
