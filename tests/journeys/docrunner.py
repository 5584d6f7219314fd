"""The README and docs/ are executable: every ``sh`` command block is run, and the figures the
text quotes from its output are checked.

A fenced block whose info string is ``sh`` is a block of commands, run with ``bash -e -o
pipefail`` in a scratch copy of the checkout with the installed venv's ``bin`` first on ``PATH``
(``smabench`` is the installed console script). HTML comments on the lines right above the fence
steer it (invisible when the Markdown is rendered):

- ``<!-- doc-run: skip REASON -->``: not run, with the reason (``make test`` would run this suite
  again; a command that needs a real device on ``/dev/ttyUSB0``). Say why in words.
- ``<!-- doc-run: timeout 600 -->``: its time limit, s (default 300).
- ``<!-- doc-check: REGEX => VALUE ± TOL -->`` (repeatable): the first group of REGEX in the
  block's output must be within TOL of VALUE (``TOL`` may end in ``%``: relative). A figure
  quoted in the text is either checked so, or labelled in the text as measured on another
  machine.

Blocks with another info string (output shown, TOML, Python) are text, not run.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

FENCE = re.compile(r"^```(\S*)\s*$")
DIRECTIVE = re.compile(r"^<!--\s*doc-(run|check):\s*(.*?)\s*-->\s*$")
CHECK = re.compile(
    r"^(?P<regex>.+?)\s*=>\s*(?P<value>[-+0-9.eE]+)\s*±\s*(?P<tol>[0-9.eE]+)(?P<pct>%?)$"
)
DEFAULT_TIMEOUT_S = 300.0


@dataclass(frozen=True)
class Check:
    """One quoted figure: ``regex``'s first group in the output, within ``tol`` of ``value``."""

    regex: str
    value: float
    tol: float
    relative: bool

    def verify(self, output: str) -> str:
        """'' when the output holds the figure within tolerance, else why not."""
        match = re.search(self.regex, output, flags=re.MULTILINE)
        if match is None:
            return f"no match for {self.regex!r} in the output"
        got = float(match.group(1))
        tol = abs(self.value) * self.tol / 100.0 if self.relative else self.tol
        if abs(got - self.value) > tol:
            unit = "%" if self.relative else ""
            return f"{self.regex!r}: {got}, not within ±{self.tol}{unit} of the quoted {self.value}"
        return ""


@dataclass(frozen=True)
class Block:
    """One ``sh`` block of a Markdown file."""

    path: Path
    line: int  # of the opening fence, 1-based
    script: str
    skip: str = ""
    timeout_s: float = DEFAULT_TIMEOUT_S
    checks: tuple[Check, ...] = field(default=())

    @property
    def name(self) -> str:
        return f"{self.path.name}:{self.line}"


def parse_directives(lines: list[str]) -> tuple[str, float, tuple[Check, ...]]:
    """The directives above a fence (``lines``: the comment lines, nearest last)."""
    skip, timeout_s, checks = "", DEFAULT_TIMEOUT_S, []
    for text in lines:
        kind, body = DIRECTIVE.match(text).groups()
        if kind == "run":
            word, _, rest = body.partition(" ")
            if word == "skip":
                if not rest.strip():
                    raise ValueError(f"doc-run: skip needs a reason: {text!r}")
                skip = rest.strip()
            elif word == "timeout":
                timeout_s = float(rest)
            else:
                raise ValueError(f"unknown doc-run directive {text!r}")
        else:
            m = CHECK.match(body)
            if m is None:
                raise ValueError(f"doc-check wants 'REGEX => VALUE ± TOL[%]': {text!r}")
            checks.append(Check(m["regex"], float(m["value"]), float(m["tol"]), bool(m["pct"])))
    return skip, timeout_s, tuple(checks)


def blocks(path: Path) -> list[Block]:
    """Every ``sh`` block of the Markdown file at ``path``, with its directives."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out: list[Block] = []
    k = 0
    while k < len(lines):
        m = FENCE.match(lines[k])
        if m is None:
            k += 1
            continue
        end = next((j for j in range(k + 1, len(lines)) if lines[j].startswith("```")), None)
        if end is None:
            raise ValueError(f"{path}:{k + 1}: unclosed code fence")
        if m.group(1) == "sh":
            above = []
            j = k - 1
            while j >= 0 and DIRECTIVE.match(lines[j]):
                above.insert(0, lines[j])
                j -= 1
            skip, timeout_s, checks = parse_directives(above)
            script = "\n".join(lines[k + 1 : end])
            out.append(Block(path, k + 1, script, skip, timeout_s, checks))
        k = end + 1
    return out
