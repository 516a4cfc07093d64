# Two entry points that do all the set-up themselves on a fresh machine (Python 3.11+, nothing installed):
#   make demo   creates .venv on first use, then runs the main job on the built-in synthetic data
#   make test   creates .venv on first use, then runs the test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# The stamp changes whenever the dependency files change, so `make` re-installs exactly when needed.
STAMP  := $(VENV)/.installed-$(shell cat pyproject.toml setup.py constraints.txt | sha1sum | cut -c1-12)

DEMO_DETECTOR ?= ours
DEMO_STORE    ?= results/smoke
DEMO_ARGS     ?= --detector $(DEMO_DETECTOR) --dataset m3t-synth --folds all --profile smoke --store $(DEMO_STORE)
DEMO_DATA     := $${HARNESS_DATA:-data}/m3t-synth-small-seed0

.PHONY: demo test venv clean-venv

venv: $(STAMP)

$(STAMP): pyproject.toml setup.py constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -c constraints.txt -e '.[dev]'
	@rm -f $(VENV)/.installed-*
	@touch $@

# The main job, then what its report needs (complexity profile, the two sensor-level analyses) and the report
demo: $(STAMP)
	$(BIN)/harness run $(DEMO_ARGS)
	$(BIN)/harness profile --detector $(DEMO_DETECTOR) --no-latency --no-onnx --no-fvcore --store $(DEMO_STORE)
	$(BIN)/harness sensing registration-error --dataset m3t-synth --store $(DEMO_STORE) \
		--landmarks "$(DEMO_DATA)/registration/landmarks.json"
	$(BIN)/harness sensing displacement --dataset m3t-synth --store $(DEMO_STORE)
	$(BIN)/harness report --store $(DEMO_STORE) --out reports/smoke

test: $(STAMP)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

clean-venv:
	rm -rf $(VENV)
