"""Argument types shared by the command-line front ends (argparse ``type=`` callables).

Each refuses bad text with one line naming what was expected; argparse turns that into
``error: argument --x: …`` and exit code 2.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable


def positive(kind: type = float) -> Callable[[str], float]:
    """A parser for a finite number > 0 of ``kind`` (float or int); NaN and inf refused."""

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not (v > 0 and math.isfinite(v)):
            raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
        return v

    return parse



PORT_URL_SCHEMES = ("socket", "rfc2217", "loop", "spy", "alt", "hwgrep", "cp2110")
"""pyserial's URL handlers (``serial_for_url``)."""


def port_syntax(text: str) -> str:
    """A port name's syntax only: not empty; a URL (``socket://…``) with a pyserial scheme."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty port name")
    if "://" in text:
        scheme = text.split("://", 1)[0].lower()
        if scheme not in PORT_URL_SCHEMES:
            raise argparse.ArgumentTypeError(f"{text}: unknown port URL scheme {scheme!r} "
                                             f"(pyserial: {', '.join(PORT_URL_SCHEMES)})")
    return text


def serial_port(text: str) -> str:
    """A current driver's port: a pyserial URL (``socket://…``, ``rfc2217://…``, ``loop://``)
    or a device that exists (``/dev/ttyUSB0``, a pty); checked, never opened."""
    import os

    port_syntax(text)
    if "://" in text:
        return text
    if not os.path.exists(text):
        raise argparse.ArgumentTypeError(f"{text}: no such port (is the device plugged in?)")
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text}: a folder, not a serial port")
    return text


def sensor_spec(text: str) -> str:
    """A displacement sensor's transport spec (``tcp:HOST:PORT`` or ``rtu:DEVICE[:BAUD]``),
    parsed by the driver's own parser; an RTU device must exist. Checked, never opened."""
    from smabench.drivers.displacement import parse_sensor_spec

    try:
        spec = parse_sensor_spec(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if spec.kind == "rtu":
        try:
            serial_port(spec.device)
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(f"sensor spec {text!r}: {exc}") from None
    return text


def sensor_map(text: str) -> str:
    """A register map: a shipped map's name or a map file, loaded and checked."""
    from smabench.drivers.displacement import load_map

    try:
        load_map(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


OUTPUT_HELP = "; '-' for standard output"
"""Appended to the help of every file output option (``--out``/``--json``/``--csv``)."""


def output_file(text: str) -> str:
    """A file to write: ``-`` (standard output), a new or existing file, a FIFO, a device or a
    symlink to one of those (:func:`smabench.sessions.atomic_write` writes each correctly); an
    empty name or an existing folder is refused."""
    if text == "-":
        return text
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty file name")
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    return text
