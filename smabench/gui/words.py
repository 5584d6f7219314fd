"""Plain words for what the runtime, the drivers and the libraries say (no Qt here).

The operator sees sentences, never raw JSON, exception class names, command-line options or a
serial library's message. :func:`plain` maps the messages the bench is known to produce; anything
else is cleaned (class names, JSON, option hints removed) and kept short.
"""

from __future__ import annotations

import re
from collections.abc import Callable

_Rule = tuple[re.Pattern[str], Callable[[re.Match[str]], str]]


def _rule(pattern: str, text: str | Callable[[re.Match[str]], str]) -> _Rule:
    fn = text if callable(text) else (lambda _m, t=text: t)
    return re.compile(pattern, re.IGNORECASE | re.DOTALL), fn


LOST_DRIVER = (
    "The current driver stopped answering (cable, USB or power?). Its output turns itself off; "
    "the session was closed as aborted."
)
LOST_DRIVER_IDLE = (
    "The current driver stopped answering (cable, USB or power?). Its output turns itself off; "
    "press Connect when it is back."
)
LOST_SENSOR = (
    "The displacement sensor stopped answering (cable, power or network?). The output was turned "
    "off and the session closed as aborted."
)
LOST_DRIVER_RUN = (
    "Device lost: the current driver stopped answering (cable, USB or power?). Its output turns "
    "itself off; the session was closed as aborted. Press Connect when it is back."
)
RUNTIME_DIED = (
    "The bench program stopped unexpectedly. The driver turns its output off by itself when the "
    "computer goes quiet; any running session was closed as aborted."
)

RULES: list[_Rule] = [
    _rule(r"^e-stop$", "Stopped by the E-STOP."),
    _rule(r"stopped by operator", "Stopped by the operator."),
    _rule(r"protocol completed", "Completed."),
    _rule(r"telemetry lost|driver lost|driver link (is )?(lost|down)|link lost|LinkTimeout|"
          r"LinkError",
          LOST_DRIVER),
    _rule(r"displacement sensor lost", LOST_SENSOR),
    _rule(r"runtime process (exited|is not running)|BrokenPipe", RUNTIME_DIED),
    _rule(r"mock bench (exited|did not become ready)",
          "The built-in mock bench could not start."),
    _rule(r"(could not open port|No such file or directory: '?(/dev/\S+?)'?\W|SerialException)",
          "The current driver's serial port cannot be opened: is the driver plugged in, is this "
          "the right port, and is no other program using it?"),
    _rule(r"Connection refused|timed out|No route to host|ModbusException|ConnectionException",
          "The displacement sensor does not answer: check its address, port, cable and power."),
    _rule(r"protocol '(\w+)' is a position reference",
          lambda m: f"The {m.group(1)} protocol is a position reference: choose PID, FF or "
          "FF+PID in the Controller panel, or an open-loop protocol."),
    _rule(r"protocol '(\w+)' is open loop",
          lambda m: f"The {m.group(1)} protocol sets the current directly: choose Open loop in "
          "the Controller panel, or a position reference (step, staircase, sine, triangle)."),
    _rule(r"interlock: commanded current ([\d.]+) A outside 0 … ([\d.]+) A",
          lambda m: f"Stopped by the current limit: {float(m.group(1)):.2f} A was asked for, the "
          f"limit is {float(m.group(2)):.2f} A."),
    _rule(r"interlock: estimated temperature ([\d.]+) °C above ([\d.]+)",
          lambda m: f"Stopped by the temperature limit: the wire was estimated at "
          f"{float(m.group(1)):.0f} °C, the limit is {float(m.group(2)):.0f} °C."),
    _rule(r"interlock: position ([-\d.]+) mm outside ([-\w.]+) … ([-\w.]+) mm",
          lambda m: f"Stopped by the position limits: the wire reached {float(m.group(1)):.3f} mm,"
          f" outside {m.group(2)} to {m.group(3)} mm."),
    _rule(r"current driver fault: (.*)",
          lambda m: f"The current driver reported a fault: {_clean(m.group(1))}."),
    _rule(r"maximum duration ([\d.]+) s reached",
          lambda m: f"Stopped: the session reached its maximum duration ({m.group(1)} s)."),
    _rule(r"a session is running", "A session is already running."),
    _rule(r"unreachable|not reachable|outside the reachable",
          lambda m: "The reference asks for positions the wire cannot reach under this load: "
          "lower the amplitude or move the offset."),
]


_NUM = r"-?\d+(?:\.\d+)?(?:e-?\d+)?"
_INTERVAL = re.compile(rf"([\[(])({_NUM}), ({_NUM})([\])])")
_SPAN = re.compile(rf"({_NUM}) … ({_NUM})")


def ranges_in_words(text: str) -> str:
    """Ranges written as intervals ("(0, 10]") or spans ("0 … 2.5") in a library's or the
    runtime's sentence, in :func:`range_words`' notation ("more than 0, up to 10", "0 to
    2.5")."""

    def interval(m: re.Match[str]) -> str:
        lo = f"more than {m.group(2)}," if m.group(1) == "(" else m.group(2)
        hi = f"less than {m.group(3)}" if m.group(4) == ")" else m.group(3)
        return f"{lo} {'up to' if m.group(1) == '(' else 'to'} {hi}"

    text = _INTERVAL.sub(interval, text)
    text = _SPAN.sub(lambda m: f"{m.group(1)} to {m.group(2)}", text)
    return re.sub(r"must be in (?=\S)", "must be ", text)


def _clean(text: str) -> str:
    """Drop command echoes, exception class names, JSON, option hints and errno prefixes."""
    text = ranges_in_words(text)
    text = re.sub(r"^\w+:\s+(?=[A-Z]\w*(Error|Exception|Timeout)\b)", "", text)  # "start: "
    text = re.sub(r"\b[A-Z]\w*(Error|Exception|Timeout):\s*", "", text)
    text = re.sub(r"\{.*\}", "", text, flags=re.DOTALL)
    text = re.sub(r"\((?:[^()]*--[^()]*)\)", "", text)
    text = re.sub(r"\s--[\w-]+(\s[\w|.,-]+)?", "", text)
    text = re.sub(r"\[Errno \d+\]\s*", "", text)
    text = re.sub(r"\s*\((?:[a-z_]+\.)*[a-z_]+\)", "", text)  # a setting's key: (load_kg)
    text = re.sub(r"\s+", " ", text).strip(" :;,")
    return text


def plain(text: str, limit: int = 240) -> str:
    """The operator's sentence for a runtime or library message."""
    text = str(text or "").strip()
    for pattern, fn in RULES:
        m = pattern.search(text)
        if m:
            return fn(m)
    text = _clean(text)
    if not text:
        return "Something went wrong (no details)."
    text = text[0].upper() + text[1:]
    if len(text) > limit:
        text = text[: limit - 1].rsplit(" ", 1)[0] + " …"
    return text if text.endswith((".", "…", "?", "!")) else text + "."


SENSING_RULES: list[_Rule] = [
    _rule(r"no valid reading for [\d.]+ s; control goes on with the position from the wire's "
          r"resistance",
          "The laser gives no valid reading: control goes on with the position from the wire's "
          "resistance until it is back."),
    _rule(r"displacement sensor back after [\d.]+ s", "The laser is back: control on the laser "
          "again."),
]
"""The session loop's warnings about the position feedback (the fallback on the wire's
resistance and its end), in the operator's words; the second is good news. Without the loop's
durations: those are wall-clock seconds, the sensing line's are the session's (they differ on a
mock bench run faster than real time)."""


def sensing_notice(text: str) -> tuple[str, bool] | None:
    """(the operator's sentence, whether it is good news) for a loop warning about the
    position feedback; None for any other warning (the window decides those elsewhere: a lost
    device from the status, a trip from the session's end)."""
    for k, (pattern, fn) in enumerate(SENSING_RULES):
        m = pattern.search(str(text))
        if m:
            return fn(m), k == 1
    return None


def device_lost(reason: str) -> bool:
    """Whether a session's end reason means a device is gone (the link must be reopened)."""
    return bool(re.search(r"telemetry lost|sensor lost|link lost|driver lost|LinkError|LinkTimeout|"
                          r"SerialException|could not open port", str(reason), re.IGNORECASE))


NO_ANSWER_AT_CONNECT = (
    "The current driver did not answer: check the port, the cable and the driver's power, then "
    "press Connect again."
)


def plain_connect(text: str) -> str:
    """Words for why a connection failed (nothing was running, so nothing was aborted)."""
    if device_lost(text) or re.search(r"did not answer|no answer|handshake", str(text), re.I):
        return NO_ANSWER_AT_CONNECT
    return plain(text)


def _num(v: float) -> str:
    return f"{v:g}"


def range_words(setting) -> str:
    """A setting's allowed values in one notation, the operator's words: "0 to 2.5 A", "more
    than 0, up to 10 kg", "at least 1"; '' when unbounded."""
    if setting.kind == "choice":
        return "one of " + ", ".join(setting.choices)
    lo, hi = setting.min, setting.max_value
    if lo is None and hi is None:
        return ""
    if hi is None:
        text = f"{'more than' if setting.min_open else 'at least'} {_num(lo)}"
    elif lo is None:
        text = f"{'less than' if setting.max_open else 'at most'} {_num(hi)}"
    else:
        low = f"more than {_num(lo)}," if setting.min_open else _num(lo)
        high = f"less than {_num(hi)}" if setting.max_open else _num(hi)
        text = f"{low} {'up to' if setting.min_open else 'to'} {high}"
    text = f"{text} {setting.unit}".rstrip()
    if isinstance(setting.max, str):
        from smabench.settings import SETTINGS

        text += f", and not above the {SETTINGS[setting.max].label}"
    return text


def setting_problem(setting, exc: Exception) -> str:
    """The operator's sentence for a refused value of ``setting``: its label, what was typed
    and the allowed values in :func:`range_words` (no key names, no interval brackets)."""
    reason = str(getattr(exc, "reason", exc))
    if setting.range_text and setting.range_text in reason:
        got = reason.rsplit(", got ", 1)[-1] if ", got " in reason else ""
        return f"{setting.label}: {got or 'this value'} is not allowed ({range_words(setting)})"
    return _clean(reason)


def tooltip(setting) -> str:
    """Help for a field: the schema's help, the allowed values (:func:`range_words`), the
    default; no key names."""
    parts = [setting.help]
    rng = range_words(setting)
    if rng and setting.kind != "choice":
        parts.append(f"Allowed: {rng}.")
    parts.append(f"Default: {setting.default_text}.")
    if setting.live:
        parts.append("Can change during a run.")
    return " ".join(parts)
