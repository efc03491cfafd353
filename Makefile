# Two commands on a fresh machine: `make demo` and `make test`. Everything else is a helper.
# `make demo ARGS='--duration 30'` (and `make bench ARGS='estimator'`) pass options through.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
EXTRAS := ros,bag,plot,fleet,test
ARGS ?=
# pip's own progress and notices stay off; what it warns about still shows.
PIP_INSTALL := $(BIN)/python -m pip install --quiet --progress-bar off

.PHONY: setup test demo bench lint colcon-check clean

# One line per step: the set-up takes one to two minutes on a fresh machine.
$(STAMP): setup.py setup.cfg package.xml
	@if [ ! -x $(BIN)/python ]; then \
		echo "setup: creating $(VENV) with $$($(PYTHON) --version 2>&1)"; \
		$(PYTHON) -m venv $(VENV); \
	fi
	@echo "setup: upgrading pip in $(VENV)"
	@$(PIP_INSTALL) --upgrade pip
	@echo "setup: installing ctid_ros (editable) with extras $(EXTRAS): numpy, scipy, sympy," \
		"the ROS 2 Jazzy wheels, rosbags, mcap, matplotlib, dask, pyarrow, pytest and the linters" \
		"(about a minute)"
	@$(PIP_INSTALL) -e '.[$(EXTRAS)]'
	@touch $@
	@echo "setup: done; $(BIN)/ctid, $(BIN)/ctid_node and $(BIN)/ctid_plant are ready"

setup: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest $(ARGS)

demo: $(STAMP)
	$(BIN)/python -m ctid_ros.demo $(ARGS)

bench: $(STAMP)
	$(BIN)/python -m bench $(ARGS)

lint: $(STAMP)
	$(BIN)/python -m pytest test/test_flake8.py test/test_pep257.py

# The package in a colcon workspace, as a ROS developer builds it: colcon-common-extensions from
# PyPI and ctid_ros's dependencies in a venv of their own (colcon brings pytest plugins the
# project venv should not get), a copy of the checkout in $(COLCON_DIR)/ws/src, then colcon
# build, colcon test (the whole suite, the DDS tests included) and colcon test-result.
# Not part of `make test`: it installs a second environment and runs the suite again (~5 min).
COLCON_DIR ?= /tmp/ctid_ros-colcon
COLCON_BIN := $(COLCON_DIR)/venv/bin
colcon-check:
	@echo "colcon-check: copying the checkout to $(COLCON_DIR)/ws/src/ctid_ros"
	@rm -rf $(COLCON_DIR)/ws $(COLCON_DIR)/deps && mkdir -p $(COLCON_DIR)/ws/src/ctid_ros
	@git ls-files -z --cached --others --exclude-standard | \
		xargs -0 cp --parents -t $(COLCON_DIR)/ws/src/ctid_ros
	@cp -r $(COLCON_DIR)/ws/src/ctid_ros $(COLCON_DIR)/deps
	@if [ ! -x $(COLCON_BIN)/python ]; then \
		echo "colcon-check: creating $(COLCON_DIR)/venv"; $(PYTHON) -m venv $(COLCON_DIR)/venv; \
	fi
	@echo "colcon-check: installing colcon-common-extensions and the dependencies of" \
		"ctid_ros[$(EXTRAS)] (about a minute)"
	@$(COLCON_BIN)/python -m pip install --quiet --progress-bar off colcon-common-extensions \
		'$(COLCON_DIR)/deps[$(EXTRAS)]'
	@$(COLCON_BIN)/python -m pip uninstall --quiet -y ctid_ros
	@echo "colcon-check: colcon build"
	@cd $(COLCON_DIR)/ws && . $(COLCON_BIN)/activate && colcon build
	@echo "colcon-check: colcon test (the whole suite, about 3 minutes)"
	@cd $(COLCON_DIR)/ws && . $(COLCON_BIN)/activate && colcon test && colcon test-result --verbose

clean:
	rm -rf $(VENV) build install log *.egg-info demo_output
