# Every target creates .venv and installs the project by itself (torch's CPU wheel first).
VENV := .venv
PY := $(VENV)/bin/python
QUICK ?=

.PHONY: install test reproduce map converged bench lint clean

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

# The map of where sharing pays (recipes/map.yaml: machines by what they observe x strength, every
# operator preset), each machine pretrained when missing: docs/cli.md, docs/records/results.md.
map: install
	$(VENV)/bin/dcsc map $(if $(QUICK),--quick,)

# The LunarLander protocol with the goal-blind converged machine (PPO on the paper's networks until
# the greedy machine lands >= 90% on the standard pad: docs/pretraining.md), pretrained when missing;
# the map (make map) has the pad-seeing converged machine too.
CONVERGED_LUNAR := loss.algorithm=ppo,loss.gamma=0.999,loss.gae_lambda=0.98,loss.normalize_advantage=true,\
	env.num_envs=16,collector.rollout_length=1024,ppo.minibatch_size=64,optim.lr=3.0e-4,\
	qcritic.updates_per_batch=1024,train.episodes=4000,train.checkpoint_every=200,train.stop_success=0.9,\
	train.keep_best=true

converged: install
	$(VENV)/bin/dcsc sweep --out results/converged "tasks=[lunarlander]" \
		lunarlander.pretrain.out_dir=runs/pretrain_lunarlander_converged lunarlander.pretrain.observes=blind \
		"lunarlander.pretrain.recipe=[$(CONVERGED_LUNAR)]"

bench: install
	$(PY) -m pip install -e ".[bench]"
	for b in bench/bench_*.py; do $(PY) $$b || exit 1; done
	$(PY) bench/bench_pretrain.py --task uav --frames 8000  # DDPG against SB3 (the loop above ran A2C)

lint: install
	$(PY) -m ruff check dcsc_torchrl envs recipes tests bench

clean:
	rm -rf $(VENV) results
