# Two commands on a fresh machine: `make demo` and `make test`. Both install first.
# LeRobot 0.6 needs Python 3.12: the first python3.12 that runs (PATH, then pyenv's versions).
PYTHON ?= $(shell for p in python3.12 $(HOME)/.pyenv/versions/3.12*/bin/python3.12 /usr/local/bin/python3.12; do \
	  $$p -c '' 2>/dev/null && { echo $$p; exit; }; done; echo python3.12)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PLUGIN := policies/lerobot_policy_hiveformer
DEMO_RAW := data/raw/push_buttons
DEMO_DATASET := data/lerobot/push_buttons

# LeRobot 0.6's decoder (torchcodec) loads FFmpeg's shared libraries; without them every LeRobot
# command prints a long warning and falls back to pyav. Debian 12's FFmpeg 5, installed when absent.
FFMPEG_LIBS := libavutil57 libavcodec59 libavformat59 libavfilter8 libavdevice59 libswscale6 libswresample4
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo -n)

.PHONY: install demo test bench reference reference-randomised reference-tower reference-tower-unseen reference-unseen reference-suite reference-act cards clean

install: $(STAMP)

# Re-installs only when a distribution's declaration changes.
$(STAMP): pyproject.toml $(PLUGIN)/pyproject.toml
	ldconfig -p | grep -Eq 'libavutil\.so\.(5[6-9]|6[0-9])' || \
	  ( $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $(FFMPEG_LIBS) ) || \
	  echo "FFmpeg's libraries could not be installed: LeRobot will warn that torchcodec cannot load and read with pyav"
	$(BIN)/python -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' 2>/dev/null || \
	  { rm -rf $(VENV) && $(PYTHON) -m venv $(VENV); }
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,ray]" -e "$(PLUGIN)[minilm,cpu]"
	touch $(STAMP)

# The main job on a small default: expert episodes of both splits → MCAP → LeRobot datasets.
# Re-running it resumes generation (nothing is generated twice) and rebuilds the datasets.
demo: install
	$(BIN)/demo-factory tasks
	$(BIN)/demo-factory generate --task push_buttons --split train --episodes 8 --out $(DEMO_RAW)/train
	$(BIN)/demo-factory generate --task push_buttons --split test --episodes 4 --out $(DEMO_RAW)/test
	$(BIN)/demo-factory inspect $$(ls $(DEMO_RAW)/train/*.mcap | head -n 1)
	$(BIN)/demo-factory convert --in $(DEMO_RAW) --out $(DEMO_DATASET) --repo-id demo/push_buttons --overwrite

# The browser test of `collect-instructions` needs Debian's chromium and its driver: installed here
# when absent; where that is impossible the test is skipped with a message.

test: install
	command -v chromium >/dev/null && command -v chromedriver >/dev/null || \
	  ( $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver ) || \
	  echo "chromium/chromium-driver could not be installed: the browser test will be skipped"
	$(BIN)/python -m pytest

# glibc's malloc keeps the memory tensors free instead of faulting it in again for the next tensor (CPU training steps
# up to twice as fast; docs/plugin.md): the settings reference_run.py gives lerobot-train (KEEP_FREED_MEMORY).
KEEP_FREED_MEMORY := MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=2147483647

bench: install
	$(KEEP_FREED_MEMORY) $(BIN)/python -m demo_factory.tools.bench --out bench/results.json

# The reference run (not part of `make test`): push_buttons demos (three seen variations, 40 episodes each
# and 60 more of the one-button one) → dataset → lerobot-train HiveFormer → a checkpoint every 100 steps
# evaluated on validation scenes → the best one evaluated closed loop on the test scenes, on a 2-core CPU in
# 15-50 minutes; resumes if interrupted. Results in outputs/reference/.
reference: install
	$(BIN)/python -m demo_factory.tools.reference_run --out outputs/reference

# The same chain on randomised episodes (docs/robustness.md): twice the episodes, each visual perturbation at
# probability 0.5, 3000 steps, the kept checkpoint also evaluated under every perturbation; ~35 min on 2 cores.
# Results in outputs/reference_randomised/ (robustness/ holds the table per factor).
reference-randomised: install
	$(BIN)/python -m demo_factory.tools.reference_run --perturb visual=0.5 --episodes-per-variation 80 \
		--extra-episodes 120 --steps 3000 --curve 10 --robustness --out outputs/reference_randomised

# The same chain for tower (1, 2 and 3 cubes, 80 episodes each and 80 more of the one-cube variation; history 19 =
# the longest episode; 6000 steps, the learning rate annealed from 2e-3 to 0), with a learning curve (success on the
# seen variations at 5 checkpoints); ~75-95 min on 2 cores. Results in outputs/reference_tower/.
reference-tower: install
	$(BIN)/python -m demo_factory.tools.reference_run --task tower --out outputs/reference_tower

# The same chain built to follow instructions never seen: the paper's train variations 0-99 x 6 episodes, MiniLM
# word-piece features, 8000 steps at a learning rate of 2e-3 annealed to 0 over the last 3000 with the pixel attention's
# cross-entropy beside the position loss, evaluation on its test variations (synthetic, corrupted, human-written) and
# a learning curve of seen and unseen success at 4 checkpoints; about an hour on 2 cores (figures and wall times per
# seed: docs/reference/unseen.md).
# Results in outputs/reference_unseen/.
reference-unseen: install
	$(BIN)/python -m demo_factory.tools.reference_run --unseen --out outputs/reference_unseen

# Tower built to follow instructions never seen: reference-unseen's chain and recipe on tower's paper train variations
# 0-99, its test variations named by the authors' human sentences as the unseen splits (docs/reference/tower.md).
# Results in outputs/reference_tower_unseen/.
reference-tower-unseen: install
	$(BIN)/python -m demo_factory.tools.reference_run --unseen --task tower --out outputs/reference_tower_unseen

# The paper's Table 1: one multi-task HiveFormer over the ten_tasks suite, one variation a task, success per task and
# their average beside the paper's (docs/reference/suite.md). SUITE=NAME runs another suite. Results in
# outputs/reference_<suite>/.
SUITE ?= ten_tasks
reference-suite: install
	$(BIN)/python -m demo_factory.tools.reference_run --suite $(SUITE) --out outputs/reference_$(SUITE)

# The same chain for ACT on a dense export of one variation (outputs/reference_act/).
reference-act: install
	$(BIN)/python -m demo_factory.tools.reference_run --policy act --out outputs/reference_act

# The committed cards of the standard datasets (dataset_cards/<name>/README.md + contact sheet),
# from a few freshly generated episodes per split in a temporary folder.
cards: install
	$(BIN)/python -m demo_factory.tools.cards --out dataset_cards

clean:
	rm -rf $(VENV) data outputs
