# smabench: `make run` and `make test` set up everything they need on a fresh Debian 12 machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# Debian packages: firmware toolchain + emulator, fuzzing, pty helpers, headless plotting.
APT_PACKAGES := gcc-avr avr-libc binutils-avr simavr libsimavr-dev libelf-dev pkg-config \
                clang libclang-rt-14-dev socat

.PHONY: run test test-python test-firmware firmware-build lint sysdeps venv clean bench

run: venv
	$(VENV)/bin/smabench demo

test: sysdeps venv lint firmware-build test-python test-firmware

sysdeps:
	@missing=$$(for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages: $$missing"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	fi

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

lint: venv
	$(VENV)/bin/ruff check smabench drivers tests

test-python: venv
	$(VENV)/bin/pytest -q

# the emulator tests in test-python need the .elf and the simavr harness
firmware-build: sysdeps
	$(MAKE) -C firmware elf sim

# C host tests (ASan/UBSan), the frame-decoder fuzz run, the firmware smoke test in simavr
test-firmware: sysdeps
	$(MAKE) -C firmware test

bench: venv
	$(VENV)/bin/smabench bench model

clean:
	rm -rf $(VENV) firmware/build
