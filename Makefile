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

.PHONY: setup test demo bench lint clean

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

clean:
	rm -rf $(VENV) build install log *.egg-info demo_output
