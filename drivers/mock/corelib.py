"""The real firmware core (``firmware/core``) built for the host, loaded with ctypes.

The Python stand-ins (:mod:`.firmware`, behind the pty mock and the simulated driver) run the
same C code as the ATmega328P: commands, ACK codes, lease, host timeout, latched faults, energy
budget, clamps, current loop. The core and its host HAL (``firmware/host/hal_host.c``) are one
shared library, ``libsmacore.so``.

Where it comes from (first that applies):

1. ``$SMABENCH_CORELIB``: a path to a built library;
2. ``firmware/build/host/libsmacore.so`` of this checkout (``make -C firmware host-lib``, which
   ``make firmware-build`` and ``make test`` run) when it is newer than every source;
3. otherwise the sources are compiled here with the system C compiler (``$CC`` or ``cc``) into a
   cache, ``$XDG_CACHE_HOME/smabench`` (``~/.cache/smabench``), named by a hash of the sources
   and flags: a fresh clone, ``pip install -e .`` or ``pip install .`` (the wheel ships the C
   sources as ``smabench.firmware_src``) needs nothing but a C compiler.

The core keeps its state in static variables (as on the MCU), so every device instance loads
its own private copy of the library (:func:`load_private`: a copy under a unique name, unlinked
once loaded, ``dlclose``-d when the instance is collected). Two devices in one process never
share a byte of state.
"""

from __future__ import annotations

import _ctypes
import contextlib
import ctypes
import hashlib
import importlib.util
import logging
import os
import shutil
import subprocess
import tempfile
import threading
import weakref
from pathlib import Path

log = logging.getLogger(__name__)



def _firmware_dir() -> Path:
    """The checkout's ``firmware/`` (a clone, ``pip install -e .``), else the sources a wheel
    ships as ``smabench.firmware_src`` (``pip install .``)."""
    checkout = Path(__file__).resolve().parents[2] / "firmware"
    if (checkout / "core" / "core.c").is_file():
        return checkout
    try:
        spec = importlib.util.find_spec("smabench.firmware_src")
    except ModuleNotFoundError:
        spec = None
    for location in (spec.submodule_search_locations or []) if spec else []:
        if (Path(location) / "core" / "core.c").is_file():
            return Path(location)
    return checkout


FIRMWARE_DIR = _firmware_dir()
CORE_DIR = FIRMWARE_DIR / "core"
HOST_DIR = FIRMWARE_DIR / "host"
BUILT_LIB = FIRMWARE_DIR / "build" / "host" / "libsmacore.so"
# keep equal to HOST_LIB_CFLAGS in firmware/Makefile
CORELIB_CFLAGS = (
    "-std=c11", "-O2", "-fPIC", "-shared", "-Wall", "-Wextra", "-Werror",
    '-DDEVICE_NAME="SMA-CD328-MOCK"',
)  # fmt: skip
HOST_SOURCES = ("hal_host.c", "hal_host.h")
EEPROM_BYTES = 1024
TELEMETRY_LEN = 29

_build_lock = threading.Lock()
_lib_path: Path | None = None


def _sources() -> list[Path]:
    core = sorted(CORE_DIR.glob("*.[ch]"))
    host = [HOST_DIR / name for name in HOST_SOURCES]
    missing = [str(p) for p in host if not p.is_file()]
    if not core or missing:
        raise FileNotFoundError(
            f"firmware sources not found under {FIRMWARE_DIR} ({', '.join(missing) or 'core'}): "
            "the stand-in devices need a smabench checkout (pip install -e .) or "
            "SMABENCH_CORELIB pointing at a libsmacore.so built by `make -C firmware host-lib`"
        )
    return core + host


def _compile(out: Path) -> None:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        raise FileNotFoundError("no C compiler (cc) to build the firmware core for the host")
    srcs = [str(p) for p in _sources() if p.suffix == ".c"]
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    cmd = [cc, *CORELIB_CFLAGS, f"-I{CORE_DIR}", f"-I{HOST_DIR}", *srcs, "-lm", "-o", str(tmp)]
    log.info("building the firmware core for the host: %s", " ".join(cmd))
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"building {out.name} failed:\n{done.stderr}")
    os.replace(tmp, out)  # atomic: a concurrent loader sees the old file or the whole new one


def library_path() -> Path:
    """The shared library to load (building it into the cache if needed)."""
    global _lib_path
    with _build_lock:
        if _lib_path is not None and _lib_path.is_file():
            return _lib_path
        env = os.environ.get("SMABENCH_CORELIB")
        if env:
            _lib_path = Path(env)
            return _lib_path
        srcs = _sources()
        if BUILT_LIB.is_file() and BUILT_LIB.stat().st_mtime >= max(
            p.stat().st_mtime for p in srcs
        ):
            _lib_path = BUILT_LIB
            return _lib_path
        digest = hashlib.sha256(" ".join(CORELIB_CFLAGS).encode())
        for src in srcs:
            digest.update(src.name.encode() + b"\0" + src.read_bytes())
        cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "smabench"
        out = cache / f"libsmacore-{digest.hexdigest()[:16]}.so"
        if not out.is_file():
            _compile(out)
        _lib_path = out
        return _lib_path


class CoreState(ctypes.Structure):
    """Mirror of ``core_state_t`` (firmware/core/core.h); checked against its size at load."""

    _fields_ = [
        ("enabled", ctypes.c_uint8),
        ("flags", ctypes.c_uint16),
        ("setpoint_ma", ctypes.c_uint16),
        ("probe_ma", ctypes.c_uint16),
        ("limit_ma", ctypes.c_uint16),
        ("host_timeout_ms", ctypes.c_uint16),
        ("lease_ms", ctypes.c_uint16),
        ("telemetry_period_ms", ctypes.c_uint16),
        ("duty", ctypes.c_uint16),
        ("current_ma", ctypes.c_uint16),
        ("voltage_dmv", ctypes.c_uint16),
        ("precise_dma", ctypes.c_uint16),
        ("supply_mv", ctypes.c_uint16),
        ("ambient_cdeg", ctypes.c_int16),
        ("tc_cdeg", ctypes.c_int16),
        ("tc_status", ctypes.c_uint8),
        ("model_c", ctypes.c_float),
        ("rx_crc_errors", ctypes.c_uint16),
        ("rx_frame_errors", ctypes.c_uint16),
        ("telemetry_deferred", ctypes.c_uint16),
        ("last_rx_ms", ctypes.c_uint32),
        ("cal_offset_ua", ctypes.c_int16),
        ("cal_current_gain", ctypes.c_uint16),
        ("cal_voltage_gain", ctypes.c_uint16),
        ("cal_voltage_offset_uv", ctypes.c_int16),
        ("heat_r_mohm", ctypes.c_uint16),
        ("heat_c", ctypes.c_uint16),
        ("heat_g", ctypes.c_uint16),
        ("heat_tmax_dc", ctypes.c_uint16),
        ("avcc_mv", ctypes.c_uint16),
        ("cut", ctypes.c_uint8),
        ("cut_armed", ctypes.c_uint8),
    ]


class HostIO(ctypes.Structure):
    """Mirror of ``host_io_t`` (firmware/host/hal_host.h): the HAL's inputs and outputs."""

    _fields_ = [
        ("millis", ctypes.c_uint32),
        ("adc_q4", ctypes.c_uint16 * 4),
        ("estop", ctypes.c_uint8),
        ("xadc_present", ctypes.c_uint8),
        ("xadc_code", ctypes.c_int16 * 2),
        ("tc_bus_ok", ctypes.c_uint8),
        ("tc_word", ctypes.c_uint32),
        ("pwm_duty", ctypes.c_uint16),
        ("output_enabled", ctypes.c_uint8),
        ("watchdog_feeds", ctypes.c_uint32),
        ("cut_latch", ctypes.c_uint8),
        ("cut_hold", ctypes.c_uint8),
        ("cut_feeds", ctypes.c_uint32),
        ("cut_clears", ctypes.c_uint32),
    ]


def _dlclose(handle: int) -> None:
    with contextlib.suppress(OSError, AttributeError):  # else the copy stays mapped
        _ctypes.dlclose(handle)


class Core:
    """One private instance of the firmware core and its host HAL.

    ``core_init`` is called by :meth:`init`; afterwards :attr:`io` (inputs/outputs),
    :attr:`state` and :attr:`eeprom` are views into this instance's memory."""

    def __init__(self) -> None:
        src = library_path()
        # a unique file (dlopen shares a path or an inode), unlinked once loaded: nothing is left
        # in the temporary folder even when the process is killed (a folder per process was,
        # 400 of them on this machine after a few days of tests that SIGKILL a mock bench)
        fd, name = tempfile.mkstemp(prefix="smabench-core-", suffix=".so")
        copy = Path(name)
        with os.fdopen(fd, "wb") as out, open(src, "rb") as lib_in:
            shutil.copyfileobj(lib_in, out)
        try:
            # PyDLL: the calls keep the interpreter lock. Each is a few µs of C that never
            # blocks; CDLL dropped and re-took the lock around every one, several per 1 ms step,
            # and beside the mock's other threads each re-take waited (a step cost 72-108 µs
            # instead of 21 µs, the device thread 79 % of a core at 5×)
            lib = ctypes.PyDLL(str(copy), mode=os.RTLD_LOCAL)
        finally:
            copy.unlink(missing_ok=True)
        self._lib = lib
        weakref.finalize(self, _dlclose, lib._handle)
        lib.host_io.restype = ctypes.POINTER(HostIO)
        lib.host_eeprom.restype = ctypes.POINTER(ctypes.c_uint8 * EEPROM_BYTES)
        lib.core_state.restype = ctypes.POINTER(CoreState)
        lib.host_state_size.restype = ctypes.c_uint32
        lib.host_io_size.restype = ctypes.c_uint32
        lib.host_rx_push.restype = ctypes.c_uint32
        lib.host_rx_push.argtypes = (ctypes.c_char_p, ctypes.c_uint32)
        lib.host_rx_pending.restype = ctypes.c_uint32
        lib.host_tx_take.restype = ctypes.c_uint32
        lib.host_tx_take.argtypes = (ctypes.c_char_p, ctypes.c_uint32)
        lib.host_telemetry.argtypes = (ctypes.c_char_p,)
        lib.host_init.argtypes = (ctypes.c_uint8,)
        lib.core_latch_fault.argtypes = (ctypes.c_uint16,)
        for name, mirror, size in (
            ("core_state_t", CoreState, lib.host_state_size()),
            ("host_io_t", HostIO, lib.host_io_size()),
        ):
            if ctypes.sizeof(mirror) != size:
                raise RuntimeError(
                    f"{name} is {size} bytes in the library, {ctypes.sizeof(mirror)} in "
                    f"{__name__}: update the mirror to firmware/core/core.h / host/hal_host.h"
                )
        self.io: HostIO = lib.host_io().contents
        self.eeprom = lib.host_eeprom().contents
        self.state: CoreState = lib.core_state().contents
        self.poll = lib.core_poll
        self.control_tick = lib.core_control_tick
        self.latch_fault = lib.core_latch_fault
        self._tx = ctypes.create_string_buffer(4096)

    def init(self, was_watchdog_reset: bool = False) -> None:
        self._lib.host_init(1 if was_watchdog_reset else 0)

    def rx_push(self, data: bytes) -> int:
        return self._lib.host_rx_push(data, len(data))

    def rx_pending(self) -> int:
        return self._lib.host_rx_pending()

    def tx_take(self) -> bytes:
        n = self._lib.host_tx_take(self._tx, len(self._tx))
        return ctypes.string_at(self._tx, n) if n else b""

    def telemetry_payload(self) -> bytes:
        out = ctypes.create_string_buffer(TELEMETRY_LEN)
        self._lib.host_telemetry(out)
        return out.raw
