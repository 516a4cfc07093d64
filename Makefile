# Two entry points that do all the set-up themselves on a fresh machine (Python 3.11+, nothing installed):
#   make demo   creates .venv on first use, then runs the main job on the built-in synthetic data
#   make test   creates .venv on first use, then runs the test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# The stamp changes whenever the dependency files change, so `make` re-installs exactly when needed.
STAMP  := $(VENV)/.installed-$(shell cat pyproject.toml setup.py constraints.txt | sha1sum | cut -c1-12)

DEMO_ARGS ?= --detector ours --dataset m3t-synth --folds all --profile smoke

.PHONY: demo test venv clean-venv

venv: $(STAMP)

$(STAMP): pyproject.toml setup.py constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -c constraints.txt -e '.[dev]'
	@rm -f $(VENV)/.installed-*
	@touch $@

demo: $(STAMP)
	$(BIN)/harness run $(DEMO_ARGS)

test: $(STAMP)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

clean-venv:
	rm -rf $(VENV)
