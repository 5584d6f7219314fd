"""Argument types shared by the command-line front ends (argparse ``type=`` callables).

Each refuses bad text with one line naming what was expected; argparse turns that into
``error: argument --x: …`` and exit code 2.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable


def positive(kind: type = float) -> Callable[[str], float]:
    """A parser for a number > 0 of ``kind`` (float or int)."""

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        return v

    return parse



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
