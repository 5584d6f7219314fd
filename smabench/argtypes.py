"""Argument types shared by the command-line front ends (argparse ``type=`` callables).

Each refuses bad text with one line naming what was expected; argparse turns that into
``error: argument --x: …`` and exit code 2.
"""

from __future__ import annotations

import argparse
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

