# Two entry points that do all the set-up themselves on a fresh machine (Python 3.11+, nothing installed):
#   make demo   creates .venv on first use, then runs the main job on the built-in synthetic data
#   make test   creates .venv on first use, then runs the test suite
#   make benchmark  the reference benchmark (273 CPU-min measured: 2 h 42 min on 2 shared cores; resumable), then its report
#   make benchmark-rgbt-tiny  the cross-dataset reference benchmark on the RGBT-Tiny-like stand-in, then its report
#   make lint   creates .venv on first use, then runs ruff (lint and format check) over the tree and mypy over harness/
#   make lock   refreshes the lock files below (tools/lock.py): run it after changing constraints.txt or the
#               dependencies in pyproject.toml, and commit the lock files it rewrites
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# The locked environment: every package the set-up installs, at one version each, with the sha256 of its file
# (written by `make lock` from constraints.txt, the hand-set pins, and pyproject.toml). `make demo` installs
# requirements.lock; `make test` and `make lint` add requirements-dev.lock (the dev extra, and tidecv). The hashes are
# for Linux x86-64, CPython 3.11; with another platform or Python the same pins are installed without them.
LOCK     := requirements.lock
DEV_LOCK := requirements-dev.lock
# torch is installed in a step of its own, after the lock: by default the CPU build of the release the lock was made
# with. On a GPU machine, swap in a CUDA build of the same release from the PyTorch CUDA wheel index for your CUDA
# version (the lock's packages stay as pinned; the CUDA libraries come with torch, unlocked):
#   make clean-venv && make venv TORCH_INDEX='--index-url URL'
# TORCH takes any pip requirement, a local wheel file included.
TORCH       ?= torch==2.13.0
TORCH_INDEX ?=
# The stamp changes whenever the dependency files or the torch choice change, so `make` re-installs exactly when needed.
HASH   := $(shell { cat pyproject.toml setup.py $(LOCK) $(DEV_LOCK); echo '$(TORCH) $(TORCH_INDEX)'; } | sha1sum | cut -c1-12)
STAMP  := $(VENV)/.installed-$(HASH)
# `make test` and `make lint` also need the dev extra (pytest, ray, submitit, the trackers, ruff, mypy); `make demo`
# only the harness itself
DEV_STAMP := $(VENV)/.installed-dev-$(HASH)
# $(call install_lock,FILE): FILE's pins, each without its dependencies (the lock lists them all), with the hashes
# checked where they apply
HASHES_APPLY := import sys, sysconfig; \
  sys.exit(sysconfig.get_platform() != "linux-x86_64" or sys.implementation.cache_tag != "cpython-311")
define install_lock
	@if $(BIN)/python -c '$(HASHES_APPLY)'; then \
	  echo "$(BIN)/python -m pip install --require-hashes --no-deps -r $(1)"; \
	  $(BIN)/python -m pip install --require-hashes --no-deps -r $(1); \
	else \
	  echo "venv: the hashes in $(1) are for Linux x86-64, CPython 3.11, not this Python:" \
	    "installing the same pins without hashes" >&2; \
	  sed 's/ --hash=.*//' $(1) > $(VENV)/$(1).nohash && \
	  $(BIN)/python -m pip install --no-deps -r $(VENV)/$(1).nohash; \
	fi
endef
# pip check, less the one gap left on purpose: tidecv asks for the GUI build of OpenCV (see requirements-dev.lock)
PIP_CHECK := $(BIN)/python -m pip check | grep -v -e '^No broken requirements' -e '^tidecv .* requires opencv-python,' \
  >&2 && { echo "venv: pip check found the broken requirements above" >&2; exit 1; } || true

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
# reference results were made with them on an AMD EPYC: a cell reruns to the same digits on that CPU model, and on
# others within the references' training variance, as `harness benchmark rerun` judges; set BENCH_ISA=native to use
# the CPU's own). Then its report, with the paper's claims tested.
BENCH_STORE ?= results/benchmark
BENCH_OUT   ?= reports/benchmark
# its cross-dataset suite (docs/benchmark.md#cross-dataset-suite): the RGBT-Tiny-like stand-in, written on first use
TINY_STORE  ?= results/benchmark-rgbt-tiny
TINY_OUT    ?= reports/benchmark-rgbt-tiny
BENCH_ISA   ?= avx2
BENCH_ENV   := $(if $(filter avx2,$(BENCH_ISA)),ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2,)
# the shipped reference results, shown beside the demo's own runs once they are in the checkout; when the demo's
# samples differ from theirs (another OpenCV release, say), the report is written without them and says why. Only
# the demo's dataset: the cross-dataset references' section would add 1 min 43 s to the report (its bootstrap over 30
# runs), over the demo's 5 min; `harness report --store references/rgbt-tiny-synth-benchmark --print` shows them.
DEMO_REFS   := $(if $(wildcard references/m3t-synth-benchmark/references.json),--reference-results shipped \
	--references-optional --datasets m3t-synth,)

.PHONY: demo benchmark benchmark-rgbt-tiny test lint venv clean-venv

venv: $(DEV_STAMP)

# the lock, then torch, then the harness itself from the checkout
$(STAMP): pyproject.toml setup.py $(LOCK) $(DEV_LOCK)
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(call install_lock,$(LOCK))
	$(BIN)/python -m pip install $(TORCH_INDEX) '$(TORCH)'
	$(BIN)/python -m pip install --no-deps -e .
	@$(PIP_CHECK)
	@rm -f $(VENV)/.installed-*
	@touch $@

$(DEV_STAMP): $(STAMP)
	$(call install_lock,$(DEV_LOCK))
	@$(PIP_CHECK)
	@touch $@

# Resolve again (torch, the harness and its dev extra, with constraints.txt's pins) and rewrite the lock files with
# their hashes; needs Python 3.11 on Linux x86-64 (PYTHON=...) and the package registry. LOCK_ARGS: see
# `python3 tools/lock.py --help`.
.PHONY: lock
lock:
	$(PYTHON) tools/lock.py $(LOCK_ARGS)

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
	$(BIN)/harness report --store $(DEMO_STORE) --out $(DEMO_OUT) --resamples 200 --workers 2 $(DEMO_REFS)

benchmark: $(STAMP)
	$(BIN)/harness prepare --dataset m3t-synth
	$(BENCH_ENV) $(BIN)/harness benchmark run --store $(BENCH_STORE)
	$(BIN)/harness report --store $(BENCH_STORE) --out $(BENCH_OUT) --resamples 1000 --workers 2

benchmark-rgbt-tiny: $(STAMP)
	$(BENCH_ENV) $(BIN)/harness benchmark run --suite rgbt-tiny-synth --store $(TINY_STORE)
	$(BIN)/harness report --store $(TINY_STORE) --out $(TINY_OUT) --resamples 1000 --workers 2

test: $(DEV_STAMP)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# settings: [tool.ruff] and [tool.mypy] in pyproject.toml
lint: $(DEV_STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy harness

clean-venv:
	rm -rf $(VENV)
