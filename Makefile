# smabench: `make run` and `make test` set up everything they need on a fresh Debian 12 machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# Debian packages: firmware toolchain + emulator, fuzzing, pty helpers, Qt offscreen + Xvfb,
# libfaketime (tests/faults: the wall clock stepped under a running session).
APT_PACKAGES := gcc-avr avr-libc binutils-avr simavr libsimavr-dev libelf-dev pkg-config \
                clang libclang-rt-14-dev socat avrdude arduino-core-avr \
                libegl1 libgl1 libx11-6 libdbus-1-3 libfontconfig1 libfreetype6 libglib2.0-0 \
                libxkbcommon0 xvfb xauth libxcb-cursor0 libxcb-icccm4 libxcb-image0 \
                libxcb-keysyms1 libxcb-render-util0 libxcb-render0 libxcb-shape0 libxcb-util1 \
                libxcb-xkb1 libxkbcommon-x11-0 libxtst6 ngspice libfaketime

.PHONY: run test test-python test-firmware firmware-build lint sysdeps venv clean bench

# with a display: the GUI on the built-in mock bench; without: a headless session on it
run: sysdeps venv
	@if [ -n "$$DISPLAY$$WAYLAND_DISPLAY" ]; then $(VENV)/bin/smabench gui --mock; \
	else $(VENV)/bin/smabench demo; fi

# the firmware's tests (74 s, 60 of them a fixed-time fuzz run on one core) beside the Python
# tests rather than after them: passes beside two CPU-bound processes; its output after theirs
test: sysdeps venv lint firmware-build
	@$(MAKE) --no-print-directory test-firmware > $(VENV)/test-firmware.log 2>&1 & fw=$$!; \
	$(MAKE) --no-print-directory test-python; py=$$?; \
	wait $$fw; fw_rc=$$?; cat $(VENV)/test-firmware.log; \
	if [ $$fw_rc -ne 0 ]; then echo "make test-firmware failed (exit $$fw_rc)"; fi; \
	exit $$(( py != 0 || fw_rc != 0 ))

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
	$(PY) -m pip install -q --upgrade pip uv
	$(PY) -m uv pip install -q --python $(PY) -e '.[dev]'
	touch $(STAMP)

lint: venv
	$(VENV)/bin/ruff check smabench drivers tests firmware/hardware sessions/samples

# two workers, a test file each at a time (module fixtures stay in one process), except that the
# tests starting a real-time bench form one group, run one after another in one worker
# (tests/conftest.py REALTIME_GROUP): the analysis files' fits use the other core meanwhile
test-python: venv
	$(VENV)/bin/pytest -q -n 2 --dist loadgroup --durations=20

# the emulator tests in test-python need the .elf, the simavr harness and the watchdog image
firmware-build: sysdeps
	$(MAKE) -C firmware elf sim wdt-elf host-lib

# C host tests (ASan/UBSan), the frame-decoder fuzz run, the firmware smoke test in simavr
# 30 s of fuzzing here, not the firmware Makefile's 60: it runs beside the Python tests on a 2-core
# machine, a whole core for its duration, inside the 20-minute CI budget (make -C firmware fuzz: 60)
test-firmware: sysdeps
	$(MAKE) -C firmware test FUZZ_SECONDS=30

bench: venv
	$(VENV)/bin/smabench bench model

clean:
	rm -rf $(VENV) firmware/build
