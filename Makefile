# Two entry points that do all the set-up themselves on a fresh machine (Python 3.11+, nothing installed):
#   make demo   creates .venv on first use, then runs the main job on the built-in synthetic data
#   make test   creates .venv on first use, then runs the test suite
#   make benchmark  the reference benchmark (85 CPU-min: about 45-75 min on 2 cores; resumable), then its report
#   make lint   creates .venv on first use, then runs ruff (lint and format check) over the tree and mypy over harness/
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# The stamp changes whenever the dependency files change, so `make` re-installs exactly when needed.
HASH   := $(shell cat pyproject.toml setup.py constraints.txt | sha1sum | cut -c1-12)
STAMP  := $(VENV)/.installed-$(HASH)
# `make test` and `make lint` also need the dev extra (pytest, ray, submitit, the trackers, ruff, mypy); `make demo`
# only the harness itself
DEV_STAMP := $(VENV)/.installed-dev-$(HASH)

# The demo benchmark: four detectors at the demo sizes (configs/profiles/demo.yaml, configs/demo/<detector>.yaml) on
# all four folds, in two lanes of folds that train side by side (one torch thread each, one lane per core; the first
# lane then runs the two sensor-level analyses, which need no training, while the second trains ours without a
# thermal channel on P1 for the encoding ablation: the lanes finish together); then the ablation table and the
# report. Finished runs are skipped; each keeps only the weights that predicted its held-out fold.
DEMO_DETECTORS ?= ours eme icafusion cmadet
DEMO_STORE     ?= results/demo
DEMO_OUT       ?= reports/demo
DEMO_RUN       := --dataset m3t-synth --profile demo --store $(DEMO_STORE) --keep-weights final
DEMO_DATA      := $${HARNESS_DATA:-data}/m3t-synth-small-seed0

# The reference benchmark (docs/benchmark.md): the four detectors x four folds x seeds 0,1,2 and the encoding ablation
# at the benchmark profile, one lane per core, resumed where it stopped; torch's AVX2 kernels by default (the shipped
# reference results were made with them, so a cell reruns to the same digits on any x86 CPU with AVX2; set
# BENCH_ISA=native to use the CPU's own). Then its report, with the paper's claims tested.
BENCH_STORE ?= results/benchmark
BENCH_OUT   ?= reports/benchmark
BENCH_ISA   ?= avx2
BENCH_ENV   := $(if $(filter avx2,$(BENCH_ISA)),ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2,)
# the shipped reference results, shown beside the demo's own runs once they are in the checkout; when the demo's
# samples differ from theirs (another OpenCV release, say), the report is written without them and says why
DEMO_REFS   := $(if $(wildcard references/m3t-synth-benchmark/references.json),--reference-results shipped \
	--references-optional,)

.PHONY: demo benchmark test lint venv clean-venv

venv: $(DEV_STAMP)

$(STAMP): pyproject.toml setup.py constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -c constraints.txt -e .
	@rm -f $(VENV)/.installed-*
	@touch $@

$(DEV_STAMP): $(STAMP)
	$(BIN)/python -m pip install -c constraints.txt -e '.[dev]'
	$(BIN)/python -m pip install --no-deps 'tidecv==1.0.1'
	@touch $@

demo: $(STAMP)
	$(BIN)/harness prepare --dataset m3t-synth
	@lane() { folds=$$1; shift; bad=0; for d in $(DEMO_DETECTORS); do \
	    $(BIN)/harness run --detector $$d --folds $$folds $(DEMO_RUN) --config configs/demo/$$d.yaml --no-progress \
	      > /dev/null || { echo "demo: $$d on $$folds FAILED" >&2; bad=1; }; done; "$$@" || bad=1; return $$bad; }; \
	sensing() { $(BIN)/harness sensing registration-error --dataset m3t-synth --store $(DEMO_STORE) \
	    --landmarks "$(DEMO_DATA)/registration/landmarks.json" && \
	  $(BIN)/harness sensing displacement --dataset m3t-synth --store $(DEMO_STORE); }; \
	lane P1,P2 sensing & a=$$!; \
	lane P3,P4+P5 $(BIN)/harness run --detector ours --encoding none --folds P1 $(DEMO_RUN) \
	  --config configs/demo/ours.yaml --no-progress > /dev/null & b=$$!; \
	fail=0; wait $$a || fail=1; wait $$b || fail=1; exit $$fail
	$(BIN)/harness ablate --detector ours --encodings none,c2 --folds P1 $(DEMO_RUN) --config configs/demo/ours.yaml \
		--no-progress
	$(BIN)/harness report --store $(DEMO_STORE) --out $(DEMO_OUT) --resamples 50 --workers 2 $(DEMO_REFS)

benchmark: $(STAMP)
	$(BIN)/harness prepare --dataset m3t-synth
	$(BENCH_ENV) $(BIN)/harness benchmark run --store $(BENCH_STORE)
	$(BIN)/harness report --store $(BENCH_STORE) --out $(BENCH_OUT) --workers 2

test: $(DEV_STAMP)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# settings: [tool.ruff] and [tool.mypy] in pyproject.toml
lint: $(DEV_STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy harness

clean-venv:
	rm -rf $(VENV)
