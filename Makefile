# `make demo` and `make test` do every set-up step themselves on a fresh machine.
SHELL := /bin/bash
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.setup-stamp
APT_PACKAGES := libosmesa6 libegl1 libegl-mesa0 libgl1-mesa-dri libglu1-mesa chromium chromium-driver fonts-dejavu-core fonts-wqy-zenhei
# Blender only checks that an exported BVH imports into a real DCC tool: `make test` installs it, `make demo` does not.
TEST_APT_PACKAGES := blender
SHARED_DATA ?= $(abspath ../shared/data)
export GRADIO_ANALYTICS_ENABLED := False
export HF_HUB_OFFLINE := 1
export HF_HUB_DISABLE_TELEMETRY := 1
export TRANSFORMERS_OFFLINE := 1

.PHONY: setup system-deps test-deps demo test test-fast student clean

define apt_install
	@missing=""; for p in $(1); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $(2) $$missing >/dev/null; \
	fi
endef

system-deps:
	$(call apt_install,$(APT_PACKAGES),)

# A machine that cannot install Blender still runs the suite: the Blender test then skips and says why.
test-deps:
	-$(call apt_install,$(TEST_APT_PACKAGES),--no-install-recommends)

$(STAMP): requirements.txt pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -r requirements.txt
	# pyrender pins PyOpenGL 3.1.0, which cannot create OSMesa contexts; 3.1.10 can.
	$(BIN)/pip install -q --no-deps PyOpenGL==3.1.10
	$(BIN)/pip install -q --no-deps -e .
	touch $(STAMP)

setup: system-deps $(STAMP)

demo: setup
	$(BIN)/python -m app

test: setup test-deps
	$(BIN)/ruff check salad app tests
	SALAD_SHARED_DATA=$(SHARED_DATA) $(BIN)/python -m pytest -q -rs --junitxml=test-artifacts/junit.xml

test-fast: setup
	SALAD_SHARED_DATA=$(SHARED_DATA) $(BIN)/python -m pytest -q -m "not slow and not browser"

# Redistil the consistency student from assets/model's teacher as the embedded one was made: two stages (~1.5 h on
# 2 threads; run it again after an interruption and it resumes). Needs data/bandai-hml (README, Data). The student
# lands in runs/consistency_rare_rows_adversarial; measure it before copying it to assets/model.
student: setup
	$(BIN)/salad train consistency --config configs/consistency_fresh_rare_rows_cpu.toml --teacher assets/model
	$(BIN)/salad train consistency --config configs/consistency_adversarial_rare_cpu.toml --teacher assets/model \
	    --init-from runs/consistency_fresh_rare_rows/model --out-dir runs/consistency_rare_rows_adversarial

clean:
	rm -rf $(VENV) test-artifacts .pytest_cache
