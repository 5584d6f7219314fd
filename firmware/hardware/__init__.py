"""The reference current driver's electrical parameters (installed as ``smabench.hardware``).

``electrical.toml`` beside this file is the one source of truth; the firmware reads it through
the generated ``firmware/core/electrical.h`` (:mod:`.gen_header`), the simavr harness includes
that header, and the Python mock and plant read :data:`ELECTRICAL` and :class:`LinearSink`.
The circuit, the parts and the wiring: ``README.md`` beside this file.
"""

from __future__ import annotations

from smabench.hardware.electrical import ELECTRICAL, Electrical, load_electrical
from smabench.hardware.sink import LinearSink, SinkState

__all__ = ["ELECTRICAL", "Electrical", "LinearSink", "SinkState", "load_electrical"]
