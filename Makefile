# Each target builds its own virtual environment on first use.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip -q --disable-pip-version-check
# uv installs what pip would in a little over half the time (55 s against 95 s for the test
# environment); where uv cannot be had, pip does it. uv takes pip's local wheels from the same place,
# and compiles the bytecode as pip does: where PYTHONDONTWRITEBYTECODE is set, every process would
# otherwise compile torch and the rest from source (the suite took 904 s instead of 784).
export UV_FIND_LINKS ?= $(PIP_FIND_LINKS)
export UV_COMPILE_BYTECODE ?= 1
DEV_EXTRAS := train,test,mcu,betaflight,blackbox
INSTALL = if $(PY) -m uv --version >/dev/null 2>&1; then $(PY) -m uv pip install -q --python $(PY) $(1); \
	else $(PIP) install $(1); fi

.PHONY: demo test lint bench clean mcu-tools

$(VENV)/.runtime: pyproject.toml
	python3 -m venv $(VENV)
	$(PIP) install uv || echo "uv not installed: pip installs instead"
	$(call INSTALL,-e .)
	touch $@

# torch goes in first and pinned, so stable-baselines3 does not pull a CUDA build.
$(VENV)/.dev: $(VENV)/.runtime
	$(call INSTALL,torch==2.13.0)
	$(call INSTALL,-e '.[$(DEV_EXTRAS)]')
	touch $@

# The Cortex-M4F cross compiler, newlib and QEMU for the C-export tests (Debian packages).
# Installs only what is missing; without apt (or the rights to use it) it says so and the
# tests that need the tools skip with the reason (in CI, where CI is set, they fail instead).
MCU_PACKAGES := gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm
mcu-tools:
	@if command -v arm-none-eabi-gcc >/dev/null && command -v arm-none-eabi-size >/dev/null \
	    && command -v qemu-system-arm >/dev/null \
	    && [ -f "$$(arm-none-eabi-gcc -print-file-name=libm.a)" ]; then :; \
	elif ! command -v apt-get >/dev/null; then \
	    echo "mcu-tools: apt-get not available; install $(MCU_PACKAGES) by hand (the MCU tests skip without them)"; \
	else \
	    SUDO=$$([ "$$(id -u)" -eq 0 ] || echo sudo); \
	    echo "mcu-tools: installing $(MCU_PACKAGES)"; \
	    { $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $(MCU_PACKAGES); } \
	    || echo "mcu-tools: could not install $(MCU_PACKAGES) (the MCU tests skip without them)"; \
	fi

demo: $(VENV)/.runtime
	$(VENV)/bin/fcemu demo

test: $(VENV)/.dev mcu-tools
	$(PY) -m ruff check .
	$(PY) -m tests.suite -q

bench: $(VENV)/.dev
	$(VENV)/bin/fcemu bench sim
	$(VENV)/bin/fcemu bench loop --controller pid --seconds 30

clean:
	rm -rf $(VENV) build *.egg-info
