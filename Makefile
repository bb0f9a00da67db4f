# Set-up is part of every target: a fresh machine needs only python3, pip and make.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl

.PHONY: setup test test-slow lint train bench clean
RUN ?= runs/reach

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# The CPU build of torch, never a CUDA wheel (PyPI's Linux torch brings CUDA):
	# 2.13.0+cpu from the wheels pip already finds here, else PyTorch's CPU index
	# (2.13.0+cpu on Linux; macOS wheels carry no local version and have no CUDA).
	$(PY) -m pip install --quiet "torch==2.13.0+cpu" 2>/dev/null || \
		$(PY) -m pip install --quiet "torch==2.13.0" --index-url https://download.pytorch.org/whl/cpu
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

setup: $(STAMP)

test: $(STAMP)
	$(PY) -m ruff check bioscara_gym training tests benchmarks
	$(PY) -m pytest -n 2 -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

# The main job: train Reach with the default config, evaluate it, say where everything is.
# It trains anew each time, replacing the run in $(RUN) (bioscara train refuses to
# start a new run in a folder that holds one).
train: $(STAMP)
	rm -rf $(RUN)
	$(VENV)/bin/bioscara train --env Bioscara-Reach --out $(RUN)
	$(VENV)/bin/bioscara eval --model $(RUN)/model.zip --episodes 100 \
		--video $(RUN)/reach.mp4 --json $(RUN)/eval.json
	@echo "model:    $(RUN)/model.zip (+ metadata.json)"
	@echo "logs:     $(RUN)/tb   (tensorboard --logdir $(RUN)/tb)"
	@echo "video:    $(RUN)/reach.mp4 (first 3 evaluation episodes)"
	@echo "results:  $(RUN)/eval.json"

lint: $(STAMP)
	$(PY) -m ruff check bioscara_gym training tests benchmarks

# fetch_push_reference.py is train_task.py's --fetch-minutes: it needs a MuJoCo 3 prefix of its own.
bench: $(STAMP)
	for b in $(filter-out benchmarks/fetch_push_reference.py,$(wildcard benchmarks/*.py)); do \
		$(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) runs .pytest_cache
