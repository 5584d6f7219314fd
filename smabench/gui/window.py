"""The operator's main window.

Layout: a run bar that never scrolls (E-STOP, state, Connect, Start/Pause/Stop, progress, the
latched e-stop banner, the message line, live readouts); below it the settings (tabs:
Experiment, Limits, Controller, Connection) beside the live plots, the sessions list and the
replay view.

The bench runtime runs in its own process (:class:`~smabench.gui.link.RuntimeLink`); this window
sends commands and draws what the runtime streams, from a 30 Hz timer. The E-STOP (button, or
Esc/F12/Ctrl+E anywhere, :mod:`smabench.gui.estop`) writes to the runtime's pipe first, before
anything is drawn; the runtime turns the driver's output off from outside its loop. Fits,
exports and file reading run off the GUI thread (:class:`~smabench.gui.sessions_view.Jobs`).
The window's state is :class:`~smabench.gui.state.StateMachine`'s; controls follow it. The
widgets are built by :class:`~smabench.gui.layout.WindowLayout`; the Sessions tab's behaviour is
:class:`~smabench.gui.sessions_view.SessionsMixin`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from smabench import settings as schema
from smabench.gui import words
from smabench.gui.estop import EStopGuard
from smabench.gui.fields import Field
from smabench.gui.fitjob import shown_cycle
from smabench.gui.gui_gc import GuiThreadCollector
from smabench.gui.layout import MODES, WindowLayout
from smabench.gui.link import (
    LINK_COLUMNS,
    PLOT_COLUMNS,
    SELFSENSE_PLOT_COLUMNS,
    RuntimeLink,
    SampleBuffer,
    select,
)
from smabench.gui.persist import Remembered
from smabench.gui.progress import estimate, planned_cycles_s
from smabench.gui.readouts import Readouts
from smabench.gui.sessions_view import Jobs, SessionsMixin
from smabench.gui.specs import (
    GAIN_LAWS,
    OPEN_LOOP_CURRENT,
    mode_uses,
    stress_question,
)
from smabench.gui.state import IN_SESSION, NOT_CONNECTED, State, StateMachine, controls_for
from smabench.gui.trends import CycleTail
from smabench.settings import GAIN_COMPONENTS, GAIN_SETS, SettingError

log = logging.getLogger(__name__)

FRAME_MS = 33
TREND_EVERY = 15  # frames between reads of the running session's cycles.csv (0.5 s)
MODE_LABEL = dict(MODES)
STATE_TEXT = {
    State.DISCONNECTED: "Not connected", State.CONNECTING: "Connecting …",
    State.IDLE: "Connected · idle", State.STARTING: "Starting …", State.RUNNING: "Running",
    State.PAUSED: "Paused (output off)", State.ESTOPPED: "E-STOP LATCHED",
    State.ERROR: "Not connected",
}  # fmt: skip
CONNECTED = (State.IDLE, State.STARTING, State.RUNNING, State.PAUSED)
LOSS_GRACE_S = 0.3
"""Wall time the driver link may be silent before the link counts as lost
(``drivers.link.Link.link_timeout_s``): rows newer than the loss minus this are not live."""
DRAIN_S = 5.0  # after a loss mid-run, how long the runtime may take to report the session's end


class MainWindow(WindowLayout, SessionsMixin, QtWidgets.QMainWindow):
    """Everything the operator needs at the bench."""

    session_ended = QtCore.Signal(dict)
    OPEN_LOOP_KEY = OPEN_LOOP_CURRENT.key

    def __init__(self, sessions_dir: str | Path = "sessions", mock_speed: float | None = 1.0,
                 remember: bool = True) -> None:  # fmt: skip
        """``mock_speed``: None keeps the remembered one; ``remember``: False for scripts
        (benchmarks) that must neither read nor write the operator's remembered entries."""
        super().__init__()
        self.setWindowTitle("smabench")
        self.sessions_dir = Path(sessions_dir)
        self.sm = StateMachine()
        self.link: RuntimeLink | None = None
        self.link_config: dict[str, Any] | None = None
        self.pending_start: dict[str, Any] | None = None
        self.session_folder: Path | None = None  # the running session's folder
        self.session_controller = False  # the running session has a controller
        # resistance sensing (issue 26) of the running (or last) session
        self.session_selfsense = False  # it has a self-sense calibration
        self._feedback_chosen = "laser"  # its feedback as chosen (start, then the live switch)
        self._session_fallback: str | None = None  # its fallback setting
        self._fallback_since_t: float | None = None  # device time the fallback began
        self._laser_back: tuple[float, float] | None = None  # (device t, s on the estimate)
        self._on_estimate = False  # the newest row was controlled on the estimate
        self.buffer = SampleBuffer()
        self.cycle_tail = CycleTail()  # the running (or last) session's per-cycle rows
        self._frames = 0
        self.status: dict[str, Any] = {}
        self.last_end: dict[str, Any] | None = None
        self.last_error = ""
        self.last_estop: dict[str, Any] | None = None  # the runtime's X report
        self.estop_time: float | None = None
        self.frame_times_s: list[float] = []
        self.custom_gains: dict[str, list[float] | None] = {law: None for law, *_ in GAIN_LAWS}
        self.readouts = Readouts()
        self._plan_s: list[float] | None = None  # the running open-loop protocol's cycles, s
        self._time_scale = 1.0  # the connected bench's device time per wall time
        self._connect_t0: float | None = None
        self._connect_step = ""
        self._drain_until: float | None = None  # lost mid-run: waiting for the end report
        self._closing: list[Any] = []  # links being closed off the GUI thread
        self._paused_at: float | None = None
        self._paused_total_s = 0.0
        self._remaining_text = "–"
        self._question: QtWidgets.QMessageBox | None = None
        self._fresh_session = False
        self._open_current_due: float | None = None
        self.collector = GuiThreadCollector(self)  # Qt objects freed on this thread only
        self.jobs = Jobs()
        self.jobs.start_worker()  # fits' process up (and its imports done) before any run
        self.fields: dict[str, Field] = {}  # by settings-schema key
        self._build(1.0 if mock_speed is None else mock_speed)
        self._refused_for_fields = False
        for f in self.fields.values():
            f.changed.connect(self._fields_edited)
        self.guard = EStopGuard(self.estop, self, button=self.estop_button,
                                send_now=self._send_estop)
        self.timer = QtCore.QTimer(self)
        self.timer.timeout.connect(self.on_frame)
        self.timer.start(FRAME_MS)
        self.remembered = Remembered(self, enabled=remember)
        self.remembered.restore()
        if mock_speed is not None:  # the caller's (command line, tests) over the remembered
            self.mock_speed.set_value(mock_speed)
        self.refresh_sessions()
        self._apply_state()

    # ------------------------------------------------------------------ state
    def fire(self, event: str) -> State:
        state = self.sm.fire(event)
        self._apply_state()
        return state

    @property
    def state(self) -> State:
        return self.sm.state

    @property
    def running(self) -> bool:
        return self.state in IN_SESSION

    def _apply_state(self) -> None:
        st = self.state
        c = controls_for(st)
        self.state_label.setText(STATE_TEXT[st])
        self.state_label.setStyleSheet("font-size: 15px; font-weight: bold; color: %s;" % (
            "#c62828" if st in (State.ESTOPPED, State.ERROR) else "#1b5e20"
            if st in (State.RUNNING, State.PAUSED) else "#333"))  # fmt: skip
        self.connect_button.setEnabled(c.connect)
        self.connect_button.setText(c.connect_label)
        self.start_button.setEnabled(c.start)
        self.pause_button.setEnabled(c.pause)
        self.pause_button.setText("Resume" if st == State.PAUSED else "Pause")
        self.stop_button.setEnabled(c.stop)
        if st != State.ESTOPPED:
            self.show_banner(False)
        self.ack_button.setEnabled(c.acknowledge)
        self.defaults_button.setEnabled(c.session_fields)
        if st == State.CONNECTING:
            self.connect_button.setText("Cancel")
        if st in NOT_CONNECTED or st == State.CONNECTING:
            self.health.setText("not connected" if st != State.CONNECTING else "connecting …")
            self.health.setStyleSheet("")
        for f in self.fields.values():
            if f.setting.group == "connection":
                f.setEnabled(c.connection_fields)
            elif not f.setting.live:
                f.setEnabled(c.session_fields)
        for wdg in (self.use_mock, self.use_real, self.mock_effect, self.mock_thermocouple,
                    self.port_row,
                    self.sensor_kind, self.sensor_host, self.sensor_rtu_port, self.sensor_baud,
                    self.sensor_map):  # fmt: skip
            wdg.setEnabled(c.connection_fields)
        self.protocol.setEnabled(c.session_fields)
        in_run = st in (State.RUNNING, State.PAUSED)
        # the feedback switches live, but only in a session that has the estimate to switch to
        self.fields["feedback"].setEnabled(c.session_fields
                                           or (in_run and self.session_selfsense))  # fmt: skip
        self.selfsense_browse.setEnabled(c.session_fields)
        self.mock_resistivity.setEnabled(c.connection_fields)
        for b in self.mode_buttons.values():
            # mid-run only a controller session can switch law; before a run any may be chosen
            b.setEnabled(not in_run or self.session_controller)
        if not in_run:
            self.active_mode.setText("active law: – (no session running)")
        self._show_readouts()

    def _show_readouts(self) -> None:
        if self.state == State.DISCONNECTED and self.readouts.mode == "fresh":
            self.readout.setText("readouts: not connected")
            return
        self.readout.setText(self.readouts.text(time.monotonic()))
        stale = self.readouts.mode != "fresh"
        self.readout.setStyleSheet("color: #8a5a00; font-style: italic;" if stale
                                   else "color: #333;")  # fmt: skip

    # ------------------------------------------------------------------ connection
    def refresh_ports(self) -> None:
        from serial.tools import list_ports

        names = [p.device for p in list_ports.comports()]
        for combo in (self.serial_port, self.sensor_rtu_port):
            current = combo.currentText()
            combo.clear()
            combo.addItems(names)
            if current:
                combo.setCurrentText(current)

    def devices_config(self) -> dict[str, Any]:
        """What the runtime opens; ValueError in words when a field is wrong."""
        if self.use_mock.isChecked():
            speed = self.mock_speed.value()
            args = ["--load-kg", f"{self.load_field.value():g}", "--speed", f"{speed:g}"]
            for effect in filter(None, (e.strip() for e in self.mock_effect.text().split(","))):
                args += ["--effect", effect]
            if self.mock_thermocouple.isChecked():
                args += ["--thermocouple"]
            if self.mock_resistivity.currentData():
                args += ["--resistivity", self.mock_resistivity.currentData()]
            return {"mock": args, "time_scale": speed}
        if self.sensor_kind.currentText() == "TCP":
            host = self.sensor_host.text().strip()
            if not host:
                raise ValueError("enter the sensor's TCP host (Connection tab)")
            spec = f"tcp:{host}:{self.sensor_tcp_port.value()}"
        else:
            device = self.sensor_rtu_port.currentText().strip()
            if not device:
                raise ValueError("choose the sensor's RTU serial port (Connection tab)")
            spec = f"rtu:{device}:{self.sensor_baud.currentText()}"
        port = self.serial_port.currentText().strip()
        if not port:
            raise ValueError("choose the current driver's serial port (Connection tab)")
        return {"port": port, "sensor": spec, "sensor_map": self.sensor_map.currentText(),
                "unit_id": self.sensor_unit.value()}  # fmt: skip

    def connect_devices(self) -> bool:
        """Start the runtime process on the chosen devices (state ``connecting``)."""
        if self.link is not None:
            self.disconnect_devices()
        try:
            cfg = self.devices_config()
        except ValueError as exc:
            self.say(str(exc), error=True)
            return False
        self.fire("connect")
        self.link = RuntimeLink(cfg)
        self.link_config = cfg
        self._time_scale = float(cfg.get("time_scale", 1.0))
        self._connect_t0 = time.monotonic()
        self._connect_step = ("starting the bench program" if "mock" in cfg else
                              f"opening the driver on {cfg['port']}")  # fmt: skip
        self.readouts.thaw()
        self.readouts.forget()
        self._show_connecting()
        return True

    def _show_connecting(self) -> None:
        """What connecting is doing, for how long, and how to stop it."""
        if self.state != State.CONNECTING or self._connect_t0 is None:
            return
        took = time.monotonic() - self._connect_t0
        self.say(f"Connecting … {took:.0f} s: {self._connect_step}. Press Cancel to stop.")

    def cancel_connect(self) -> None:
        """Connecting stopped by the operator: the runtime (and its mock) closed, not connected."""
        if self.state != State.CONNECTING:
            return
        self._drop_link()
        self.pending_start = None
        self.fire("disconnect")
        self.say("Connecting cancelled.")

    def _drop_link(self) -> None:
        """Close the runtime link off the GUI thread (a stalled runtime must not freeze the
        window or an E-STOP key); closed for good before the window quits."""
        link, self.link = self.link, None
        self._drain_until = None
        if link is None:
            return
        import threading

        t = threading.Thread(target=link.close, name="runtime-close", daemon=True)
        t.start()
        self._closing = [c for c in self._closing if c.is_alive()] + [t]

    def disconnect_devices(self) -> None:
        self._drop_link()
        self.status = {}
        self.pending_start = None
        self.readouts.freeze("not connected", time.monotonic(), gone=True)
        if self.state != State.ESTOPPED:
            self.fire("disconnect")
        self._apply_state()

    def toggle_connection(self) -> None:
        if self.state == State.CONNECTING:
            self.cancel_connect()
        elif self.state in NOT_CONNECTED:
            self.connect_devices()
        else:
            self.disconnect_devices()

    @property
    def connected(self) -> bool:
        return self.link is not None and self.link.alive and self.link.ports is not None

    def wait_connected(self, timeout_s: float) -> bool:
        """For scripts (benchmarks): process events until connected or failed."""
        deadline = time.monotonic() + timeout_s
        while self.state == State.CONNECTING and time.monotonic() < deadline:
            QtWidgets.QApplication.processEvents(QtCore.QEventLoop.ProcessEventsFlag.AllEvents, 50)
            self.on_frame()
        return self.connected

    # ------------------------------------------------------------------ experiment
    def selected_mode(self) -> str:
        return next((m for m, b in self.mode_buttons.items() if b.isChecked()), "open_loop")

    def _v(self, name: str) -> Any:
        return self.fields[name].value()

    def field_errors(self) -> list[str]:
        """Sentences for the visible fields that are not valid (empty: all good)."""
        return [words.plain(e).rstrip(".") for f in self.visible_fields() if (e := f.error())]

    def settings_dict(self, allow_high_stress: bool = False) -> dict[str, Any]:
        """The start message from the fields (the schema's JSON shape; settings at their
        default left out), checked by the schema; ValueError in words when one is refused."""
        errors = self.field_errors()
        if errors:
            raise ValueError("; ".join(errors))
        name = self.protocol.currentText()
        mode = self.selected_mode()
        closed = mode != "open_loop"
        flat: dict[str, Any] = {"protocol.name": name}
        for key, f in self.fields.items():
            st = f.setting
            if st.key not in schema.SETTINGS or st.group == "gains":
                continue
            if st.group == "controller" and not (closed and mode_uses(st, mode)):
                continue
            if st.group == "protocol" and not st.uses(name, closed):
                continue
            v = f.value()
            if key == "selfsense" and v:  # the runtime reads it: "~" as the operator means it
                v = str(Path(v).expanduser())
            if st.required or v != st.default:
                flat[key] = v
        if closed:
            flat["controller.mode"] = mode
            for law, gs in GAIN_SETS.items():
                g = self.custom_gains[law]
                if g is not None:
                    flat.update({f"{gs.key}.{c}": v for c, v in zip(GAIN_COMPONENTS, g,
                                                                   strict=True)})  # fmt: skip
        if allow_high_stress:
            flat["allow_high_stress"] = True
        flat["out_dir"] = str(self.sessions_dir)
        if self.use_mock.isChecked() and self.mock_speed.value() != 1.0:
            flat["time_scale"] = self.mock_speed.value()
        try:  # the schema's own check: ranges and the rules across settings
            schema.check_run(schema.values_from_mapping(schema.to_mapping(flat)))
        except SettingError as exc:
            raise ValueError(words.plain(str(exc)).rstrip(".")) from None
        return schema.to_mapping(flat)

    def start_experiment(self) -> None:
        """Check the fields, confirm a high-stress load, connect if needed, send the start."""
        if not controls_for(self.state).start or self._question is not None:
            return
        errors = self.field_errors()
        if errors:
            self.say(f"Not started: {'; '.join(errors)}.", error=True)
            self._refused_for_fields = True
            return
        question = stress_question(self._v("load_kg"), self._v("wire_preset"),
                                   self._v("long_life_stress_mpa"))  # fmt: skip
        try:
            settings = self.settings_dict(allow_high_stress=bool(question))
            cfg = self.devices_config()
        except ValueError as exc:
            self.say(f"Not started: {exc}.", error=True)
            return
        if question:
            self._ask(question, lambda: self._start_with(settings, cfg))
        else:
            self._start_with(settings, cfg)

    def _ask(self, question: str, proceed: Any) -> None:
        """A yes/no question that leaves the window usable (the E-STOP button too)."""
        box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Icon.Warning, "High stress", question,
                                    QtWidgets.QMessageBox.StandardButton.Yes
                                    | QtWidgets.QMessageBox.StandardButton.No, self)  # fmt: skip
        box.setDefaultButton(QtWidgets.QMessageBox.StandardButton.No)
        box.setWindowModality(QtCore.Qt.WindowModality.NonModal)
        self._question = box

        def answered(result: int) -> None:
            self._question = None
            if result == QtWidgets.QMessageBox.StandardButton.Yes and controls_for(
                self.state
            ).start:
                proceed()
            else:
                self.say("Not started: the high-stress load was not confirmed.")

        box.finished.connect(answered)
        box.show()

    def _start_with(self, settings: dict[str, Any], cfg: dict[str, Any]) -> None:
        if self.link is not None and cfg != self.link_config:
            self.say("The connection settings changed: reconnecting first.")
            self.disconnect_devices()
        if self.state in NOT_CONNECTED:
            self.pending_start = settings
            self.connect_devices()
            return
        self._send_start(settings)

    def _send_start(self, settings: dict[str, Any]) -> None:
        self.pending_start = None
        self.fire("start")
        self.session_controller = "controller" in settings
        self.session_selfsense = settings.get("selfsense") is not None
        self._feedback_chosen = str(settings.get("feedback") or "laser")
        self._session_fallback = settings.get("fallback")
        self._fallback_since_t = self._laser_back = None
        self._on_estimate = False
        self._show_sensing()
        self._show_setting_fields()
        self.pending_settings = settings
        protocol = settings.get("protocol") or {}
        self._plan_s = None if "controller" in settings else planned_cycles_s(protocol)
        self.remembered.save()  # what was started is what the next start of the window shows
        self.readouts.wire_preset = str(self._v("wire_preset"))
        self._fresh_session = True
        self.link.start(settings)
        self.say("Starting …")

    def toggle_pause(self) -> None:
        if self.state == State.RUNNING:
            self.link.send("pause")
            self._paused_at = time.monotonic()
            self.fire("pause")
        elif self.state == State.PAUSED:
            self.link.send("resume")
            if self._paused_at is not None:
                self._paused_total_s += time.monotonic() - self._paused_at
            self._paused_at = None
            self.fire("resume")

    def pause_experiment(self, on: bool) -> None:
        if on != (self.state == State.PAUSED):
            self.toggle_pause()

    def stop_experiment(self) -> None:
        if self.link is not None and self.link.alive and self.running:
            self.link.send("stop")
            self.say("Stopping …")

    def _send_estop(self, input_t: float | None, source: str) -> bool:
        """The e-stop down the runtime's pipe (any thread: one write); whether it went."""
        link = self.link
        return link.estop(input_t, source) if link is not None else False

    def estop(self, input_t: float | None = None, source: str = "",
              sent: bool | None = None) -> None:  # fmt: skip
        """E-STOP: the runtime first (output off, session aborted), then the display.

        ``input_t``: the key press's or click's own time (``time.monotonic()``, s) when known,
        ``source`` what it was; the runtime logs both in the session's ``events.jsonl`` and the
        banner's figure is measured from it. ``sent``: the e-stop already went down the pipe
        (the keys' fast path, :mod:`smabench.gui.xkeys`) and whether it did."""
        if not source:  # the button's pressed signal: the click's time from the guard
            source = "button"
            press = self.guard.press_t if getattr(self, "guard", None) is not None else None
            if press is not None and press[1] and time.monotonic() - press[0] < 1.0:
                input_t = press[0]
        self.estop_time = time.monotonic() if input_t is None else input_t
        link = self.link
        if sent is None:
            sent = self._send_estop(input_t, source)
        self.last_estop = None
        was_lost = self.state == State.ERROR and self.readouts.why == "device lost"
        self._close_dialogs()
        self.fire("estop")
        self.readouts.freeze("E-STOP", time.monotonic(), gone=link is None,
                             temperature_c=self._newest("temperature_est_C"))
        if self.session_folder is not None or self._plan_s is not None:
            elapsed = self.times.text().split("   remaining")[0]
            self.times.setText(f"{elapsed}   stopped by the E-STOP")
        self._plan_s = None
        if sent:
            text = ("E-STOP: output off command sent to the driver; waiting for its "
                    "confirmation …")  # fmt: skip
        elif self.state == State.ESTOPPED and link is not None and link.alive:
            text = "E-STOP: the bench is still connecting; nothing was driven."
        elif was_lost:
            text = ("E-STOP: the bench was lost, so nothing can be sent; the driver turns its "
                    "output off by itself when the computer goes quiet. Check the bench.")
        else:
            text = "E-STOP: nothing is connected, so no output was on."
        self.show_banner(True, f"{text}  Press Acknowledge (beside the E-STOP) when it is safe.")
        self._show_readouts()
        self.say(text, error=True)

    def _close_dialogs(self) -> None:
        """An E-STOP closes what is open over the window: drop-downs and menus, file dialogs,
        the high-stress question (which then starts nothing)."""
        app = QtWidgets.QApplication.instance()
        for _ in range(5):
            popup = app.activePopupWidget()
            if popup is None:
                break
            popup.close()
        dialog = getattr(self, "_dialog", None)
        if dialog is not None and dialog.isVisible():
            dialog.reject()
        if self._question is not None:
            box, self._question = self._question, None
            box.finished.disconnect()
            box.reject()
        for w in app.topLevelWidgets():
            if isinstance(w, QtWidgets.QDialog) and w.isVisible():
                w.reject()

    def acknowledge_estop(self) -> None:
        if self.state != State.ESTOPPED:
            return
        self.fire("acknowledge_connected" if self.connected else "acknowledge_disconnected")
        if self.connected:
            self.readouts.thaw()
        self._show_readouts()
        self.say("E-STOP acknowledged.")

    def set_mode(self, mode: str) -> None:
        """Switch the law of a running controller session (the open-loop current first)."""
        if not (self.state in (State.RUNNING, State.PAUSED) and self.session_controller):
            return
        if mode == "open_loop":
            current = self.fields[OPEN_LOOP_CURRENT.key]
            err = current.error()
            limit = self.fields["current_limit_a"].value()
            if not err and current.value() > limit:
                err = (f"open-loop current {current.value():g} A is above the current limit "
                       f"{limit:g} A")  # fmt: skip
            if err:
                self.say(f"Not switched: {err}.", error=True)
                self.mode_buttons[self.status.get("mode", "pid")].setChecked(True)
                return
            # the controller holds the current it had when open loop is entered, so the
            # operator's current is sent after the switch (again once the status shows it)
            self.link.send(f"mode {mode}")
            self._open_current_due = current.value()
            QtCore.QTimer.singleShot(100, self._send_open_current)
            return
        self._open_current_due = None
        self.link.send(f"mode {mode}")

    def _send_open_current(self) -> None:
        if self._open_current_due is not None and self._live_controller():
            self.link.send(f"open_current {self._open_current_due:g}")

    def _gain_fields(self, law: str) -> list[Field]:
        return [self.fields[k] for k in GAIN_SETS[law].keys]

    def _show_table_gains(self) -> None:
        """Gain sets that follow the per-load table show its gains for the load (read-only)."""
        from smabench.control import gains_for_load

        if self.load_field.error():
            return
        load = self.load_field.value()
        for law in GAIN_SETS:
            table = self.custom_gains[law] is None
            g = gains_for_load(load, law=law)
            for f, v in zip(self._gain_fields(law), (g.kp, g.ki, g.kd, g.d_filter_s),
                            strict=True):  # fmt: skip
                if table:
                    f.set_value(round(v, 4))
                f.setReadOnly(table)

    def use_gain_table(self, law: str, on: bool) -> None:
        """Back to (or away from) the per-load table for one gain set; live when running."""
        label = GAIN_SETS[law].label
        if on:
            self.custom_gains[law] = None
            self._show_table_gains()
            if self._live_controller():
                from smabench.control import gains_for_load

                g = gains_for_load(self.load_field.value(), law=law)
                self.link.send(f"gains {g.kp} {g.ki} {g.kd} {law}")
                self.say(f"{label} gains: back to the per-load table, in the running session.")
            else:
                self.say(f"{label} gains: the per-load table.")
        else:
            for f in self._gain_fields(law):
                f.setReadOnly(False)
            self.say(f"{label} gains: edit them, then press Apply.")

    def apply_gains(self, law: str) -> None:
        """Use the fields' gains for ``law`` from now on (live when running)."""
        fs = self._gain_fields(law)
        bad = [f.error() or (f"{f.setting.label}: enter a value" if not f.text().strip() else "")
               for f in fs]  # fmt: skip
        bad = [b for b in bad if b]
        if bad:
            self.say(f"Gains not applied: {bad[0]}.", error=True)
            return
        self.custom_gains[law] = [f.value() for f in fs]
        box = self.gain_table_boxes[law]
        box.blockSignals(True)
        box.setChecked(False)
        box.blockSignals(False)
        for f in fs:
            f.setReadOnly(False)
        label = GAIN_SETS[law].label
        if self._live_controller():
            kp, ki, kd, _ = self.custom_gains[law]
            self.link.send(f"gains {kp} {ki} {kd} {law}")
            self.say(f"{label} gains applied to the running session (the derivative filter "
                     "changes from the next session).")  # fmt: skip
        else:
            self.say(f"{label} gains will be used from the next session.")

    # ------------------------------------------------------------------ resistance sensing
    def choose_selfsense_file(self) -> None:
        """Browse for a self-sense calibration (``smabench selfsense calibrate``'s JSON)."""
        current = self.fields["selfsense"].text().strip()
        start = str(Path(current).expanduser().parent) if current else str(Path.cwd())
        dlg = self._dialog_for("Self-sense calibration", "json", start)
        dlg.fileSelected.connect(lambda path: self.fields["selfsense"].set_value(path))
        dlg.show()

    def feedback_chosen(self) -> None:
        """The feedback choice changed: in a running session with a calibration it switches
        the controller's position source live (bumpless in the runtime); otherwise it is the
        next session's setting."""
        field = self.fields["feedback"]
        source = field.value()
        if not (self.state in (State.RUNNING, State.PAUSED) and self.session_selfsense
                and self.link is not None) or source == self._feedback_chosen:  # fmt: skip
            return
        self._feedback_chosen = source
        self._fallback_since_t = self._laser_back = None
        self.link.send(f"feedback {source}")
        self.say("Position feedback: " + ("the position from the wire's resistance"
                 if source == "resistance" else "the laser") + ", from the next control tick.")
        self._show_sensing()

    def _set_feedback_field(self, source: str) -> None:
        field = self.fields["feedback"]
        field.blockSignals(True)
        field.set_value(source)
        field.blockSignals(False)

    def _follow_feedback(self, rows) -> None:
        """The rows' ``feedback_resistance`` (from their flags): when the control went onto
        the estimate and back (device time), for :meth:`_show_sensing`."""
        t = rows[:, LINK_COLUMNS.index("t_s")]
        fb = rows[:, LINK_COLUMNS.index("feedback_resistance")]
        known = np.isfinite(fb)
        if not known.any():
            return
        t, on = t[known], fb[known] > 0.5
        before = np.concatenate([[self._on_estimate], on[:-1]])
        changes = np.flatnonzero(on != before)
        for i in changes:
            if on[i] and self._feedback_chosen == "laser":  # the fallback, not the choice
                self._fallback_since_t = float(t[i])
                self._laser_back = None
            elif not on[i] and self._fallback_since_t is not None:
                self._laser_back = (float(t[i]), float(t[i]) - self._fallback_since_t)
                self._fallback_since_t = None
        self._on_estimate = bool(on[-1])
        if changes.size:
            self._show_sensing()

    def _show_sensing(self) -> None:
        """The line beside the readouts: where the controller's position comes from (blank in
        a session without a self-sense calibration)."""
        lbl = self.sensing_label
        if not self.session_selfsense:
            lbl.setText("")
            lbl.setToolTip("")
            lbl.setStyleSheet("")
            return
        style = "color: #1a4f8a;"
        if self._feedback_chosen == "resistance":
            text = "Position from the wire's resistance (chosen)."
            tip = ("The controller's position is the one estimated from the wire's resistance, "
                   "as chosen; the laser's is recorded beside it.")
            style = "color: #1a4f8a; font-weight: bold;"
        elif self._on_estimate and self._fallback_since_t is not None:
            text = (f"LASER LOST at {self._fallback_since_t:.1f} s: position from the wire's "
                    "resistance (fallback).")
            tip = ("The laser gives no valid reading: the control goes on with the position "
                   "estimated from the wire's resistance until the laser is back (the rows are "
                   "flagged; the session ends if the laser stays away too long).")
            style = "color: #c62828; font-weight: bold;"
        elif self._laser_back is not None:
            t, gap = self._laser_back
            text = f"Laser back at {t:.1f} s, after {gap:.1f} s on the wire's resistance."
            tip = ("The laser reads again: the control is back on it (times in the session's "
                   "own seconds).")
            style = "color: #1b5e20; font-weight: bold;"
        else:
            armed = self._session_fallback == "resistance"
            text = "Position from the laser; " + ("fallback: the wire's resistance." if armed
                                                  else "no fallback.")  # fmt: skip
            tip = ("The controller's position is the laser's; the one estimated from the wire's "
                   "resistance is recorded and plotted beside it" + (
                       ", and takes over while the laser gives no valid reading." if armed
                       else "."))  # fmt: skip
        lbl.setToolTip(tip)
        lbl.setText(text)
        lbl.setStyleSheet(style)

    def _on_notice(self, text: str) -> None:
        """A warning of the session's loop (``W``): the position feedback's (the fallback on
        the wire's resistance, the laser back) on the message line in plain words, unless an
        E-STOP's message is there; any other only in the log (a lost device or a trip is
        decided from the status and the session's end, in one place)."""
        log.info("runtime warning: %s", text)
        said = words.sensing_notice(text)
        if said is None or self.state not in (State.RUNNING, State.PAUSED):
            return
        sentence, good = said
        self.say(sentence, error=not good)

    def _live_controller(self) -> bool:
        return (self.state in (State.RUNNING, State.PAUSED) and self.session_controller
                and self.link is not None)  # fmt: skip

    # ------------------------------------------------------------------ frame
    def on_frame(self) -> None:
        t0 = time.perf_counter()
        link = self.link
        if link is not None:
            rows = link.take_rows()
            if rows.size and self.state in (State.RUNNING, State.PAUSED, State.STARTING):
                # (after an E-STOP or a loss the rows still coming are not live)
                if self._fresh_session:  # the first rows of a new session
                    self._clear_live()
                self.buffer.append_rows(select(rows, self.buffer.columns))
                if self.session_selfsense:
                    self._follow_feedback(rows)
            for kind, payload in link.poll():
                if self.link is not link:  # disconnected while handling an event
                    break
                self.on_event(kind, payload)
            if self._drain_until is not None and time.monotonic() > self._drain_until:
                self._drop_link()  # the runtime did not report the lost session's end
        self.jobs.poll()
        if self.jobs.busy and not self.jobs_label.text().startswith("working"):
            self.jobs_label.setText("working … " + self.jobs_label.text())
        if self.state == State.CONNECTING and self._frames % 15 == 0:
            self._show_connecting()
        if self.tabs.currentIndex() == 0 and self.buffer.n:
            self.loop_plot.update_from(self.buffer)
            self.time_plots.update_from(self.buffer)
            if self.selfsense_plots.isVisible():
                self.selfsense_plots.update_from(self.buffer)
        self._frames += 1
        if self.session_folder is not None and self._frames % TREND_EVERY == 0:
            self.cycle_tail.read()
        if self.tabs.currentWidget() is self.trend_plots:
            self.trend_plots.update_from(self.cycle_tail)
        if self._frames % TREND_EVERY == 0 and self.readouts.mode != "fresh":
            self._show_readouts()  # the ages and the cooling estimate move on
        if self.buffer.n:
            sp = self.buffer.column("setpoint_mm")[-1]
            self.setpoint_label.setText(
                "setpoint –" if not np.isfinite(sp) else f"setpoint {sp:.3f} mm"
            )
        self.frame_times_s.append(time.perf_counter() - t0)
        del self.frame_times_s[:-1000]

    def announce(self, text: str, error: bool = False) -> None:
        """A background result (a fit, an export, a session read): beside the message line,
        never in it (an E-STOP's or a saved session's message stays) and never a change of
        view."""
        if error:
            log.warning("%s", text)
        self.jobs_label.setText(text)
        self.jobs_label.setStyleSheet("color: #c62828;" if error else "color: #1a4f8a;")

    def on_event(self, kind: str, payload: dict[str, Any]) -> None:
        if kind == "P":
            self.link.ports = payload
            self._connect_t0 = None
            self.fire("connected")
            self.readouts.thaw()
            dev = payload["device"]
            where = "mock bench" if payload.get("mock_pid") else payload["driver"]
            self.say(f"Connected: {dev['name']} ({where}).")
            if self.pending_start is not None and self.state == State.IDLE:
                self._send_start(self.pending_start)
        elif kind == "S":
            self._on_status(payload)
        elif kind == "X":
            self._on_estop_report(payload)
        elif kind == "E":
            self._on_end(payload)
        elif kind == "Q":
            self._on_runtime_gone(payload)
        elif kind == "W":
            self._on_notice(str(payload.get("text", "")))

    def _on_status(self, st: dict[str, Any]) -> None:
        if "connecting" in st:  # what the runtime is opening now
            self._connect_step = str(st["connecting"])
            self._show_connecting()
            return
        if self.state == State.ERROR:  # lost: what the runtime still says is not the bench's
            return
        if "error" in st:
            text = words.plain(st["error"])
            if st.get("command") == "feedback":  # refused: the choice shows what runs
                self._feedback_chosen = str(self.status.get("feedback") or "laser")
                self._set_feedback_field(self._feedback_chosen)
                self._show_sensing()
            if st.get("command") == "start" or self.state == State.STARTING:
                self._fresh_session = False  # a refused start leaves the plots as they were
                self._plan_s = None
                self.session_selfsense = not self.selfsense_plots.isHidden()  # the shown one's
                self._show_sensing()
                self.fire("refused")
                self.say(f"Not started: {text}", error=True)
            elif self.state != State.ESTOPPED:
                self.say(text, error=True)
            return
        if "started" in st:
            self.session_folder = Path(st["started"])
            self.cycle_tail.reset(self.session_folder)
            self.trend_plots.reset()
            self._paused_total_s, self._paused_at = 0.0, None
            if self._fresh_session:
                self._clear_live()
            self.progress.setValue(0)
            self.last_end = None
            if self.state == State.STARTING:
                self.fire("started")
                self.tabs.setCurrentIndex(0)
                self.say(f"Running; recording to {self.session_folder}")
            return
        self.status = st
        self._show_status(st)

    def _clear_live(self) -> None:
        """The live plots start over (a new session's first rows or its start)."""
        self._fresh_session = False
        self.buffer.clear(PLOT_COLUMNS + SELFSENSE_PLOT_COLUMNS if self.session_selfsense
                          else PLOT_COLUMNS)  # fmt: skip
        self.loop_plot.reset()
        self.time_plots.reset()
        self.time_plots.follow = True
        self.selfsense_plots.reset()
        self.selfsense_plots.setVisible(self.session_selfsense)

    def _show_status(self, st: dict[str, Any]) -> None:
        stats = st.get("sensor_stats", {})
        drv_ok = bool(st.get("driver_link_ok"))
        if not drv_ok and self.state in CONNECTED:
            # the one place a lost driver is decided: the whole window follows at once
            self._device_lost(words.LOST_DRIVER_RUN if self.running else words.LOST_DRIVER_IDLE)
            return
        fault = words.plain(st["driver_fault"]) if st.get("driver_fault") else ""
        if self.state not in NOT_CONNECTED:
            self.health.setText(
                f"driver {'ok' if drv_ok else 'LOST'}{' · ' + fault if fault else ''} · sensor "
                f"{stats.get('ok', 0)}/{stats.get('reads', 0)} ok, "
                f"{stats.get('timeouts', 0)} timeouts"
            )
            self.health.setStyleSheet("" if drv_ok and not fault else "color: #c62828;")
        mode = st.get("mode")
        law = MODE_LABEL.get(mode, "open loop") if st.get("running") else ""
        self.readouts.update(st.get("readout", {}), time.monotonic(), law)
        self._show_readouts()
        if st.get("running") and mode and self.state in (State.RUNNING, State.PAUSED):
            self.active_mode.setText(f"active law: {MODE_LABEL.get(mode, mode)}")
            if mode == "open_loop" and self._open_current_due is not None:
                self._send_open_current()
                self._open_current_due = None
            if self.session_controller and mode in self.mode_buttons:
                self.mode_buttons[mode].setChecked(True)
        if "progress" in st and st.get("running") and self.state in (State.RUNNING,
                                                                      State.PAUSED):
            self._show_progress(st)

    def _show_progress(self, st: dict[str, Any]) -> None:
        """Progress and remaining time: from the protocol's plan (open loop) or the reference's
        device time (controller), from the first second; frozen while paused."""
        el = float(st.get("elapsed_s", 0.0))
        cycle = int(st.get("cycle") or 0)
        if self.state == State.RUNNING:  # frozen while paused
            p = float(st["progress"])
            remaining_s: float | None = None
            if self._plan_s and self.buffer.n:
                t = self.buffer.column("t_s")
                cyc = self.buffer.column("cycle")
                k = int(np.nanmax(cyc)) if np.isfinite(cyc).any() else 0
                start = t[int(np.argmax(cyc >= k))] if k > 0 else 0.0
                p, rest_device_s = estimate(self._plan_s, float(t[-1]), k, float(start))
                remaining_s = rest_device_s / max(self._time_scale, 1e-9)
            elif p > 0:
                active = el - self._paused_total_s
                remaining_s = active / p * (1 - p)
            self.progress.setValue(int(1000 * p))
            self._remaining_text = "–" if remaining_s is None else f"{remaining_s:.0f} s"
        self.times.setText(f"elapsed {el:.0f} s   remaining {self._remaining_text}   "
                           f"cycle {shown_cycle(cycle)} of {st['cycles']} · "
                           f"{st['phase']}")  # fmt: skip

    def _on_estop_report(self, x: dict[str, Any]) -> None:
        self.last_estop = x
        if x.get("confirmed") and self.estop_time is not None:
            ms = (x["output_off_t"] - self.estop_time) * 1e3
            text = f"E-STOP: the driver reports its output off ({ms:.0f} ms after the press)."
            if x.get("current_off_t") is not None:
                ms_zero = (x["current_off_t"] - self.estop_time) * 1e3
                text = text[:-2] + f"; current below 20 mA {ms_zero:.0f} ms after it)."
        else:
            text = ("E-STOP: the driver did not confirm output off. It switches itself off "
                    "when the computer stops talking to it; check the bench.")  # fmt: skip
        if self.state == State.ESTOPPED:
            self.show_banner(True, f"{text}  Press Acknowledge (beside the E-STOP) when it is "
                             "safe.")  # fmt: skip
            self.say(text, error=not x.get("confirmed"))

    def _on_end(self, end: dict[str, Any]) -> None:
        if self.state == State.CONNECTING:  # the runtime could not open the devices
            self.last_error = words.plain_connect(end.get("reason", ""))
            return
        self.last_end = end
        self._paused_at = None
        self._plan_s = None
        status = end.get("status", "aborted")
        reason = words.plain(end.get("reason", ""))
        lost = words.device_lost(end.get("reason", ""))
        self.cycle_tail.read()  # the last cycles, written when the session closed
        self.session_folder = None
        folder = end.get("folder")
        n = end.get("samples")
        samples = f" {n} samples" if n is not None else ""
        saved = f"{samples} saved in {folder}." if folder else " Nothing was saved."
        self.refresh_sessions()
        if self.state == State.ERROR:  # lost mid-run: the runtime's report of that session
            self._not_live_after_loss(end.get("reason", ""))
            self.say(f"{self.message.text()}{saved}", error=True)
            self._drop_link()
            self.session_ended.emit(end)
            return
        if status == "completed":
            self.progress.setValue(1000)
        el = float(self.status.get("elapsed_s", 0.0))
        self.times.setText(f"elapsed {el:.0f} s   ended: {status}")
        head = "Session completed." if status == "completed" else f"Session {status}: {reason}"
        if lost:
            self.session_ended.emit(end)
            self._device_lost(f"{words.LOST_DRIVER_RUN}{saved}", end.get("reason", ""))
            return
        if self.state == State.ESTOPPED:
            pass  # the latched E-STOP's message and banner stay
        else:
            if status == "aborted":  # a trip: the numbers before it are history
                self.readouts.freeze("stopped", time.monotonic(),
                                     temperature_c=self._newest("temperature_est_C"))
            self.fire("ended")
            self.say(f"{head}{saved}", error=status != "completed")
        self.session_ended.emit(end)

    def _newest(self, column: str) -> float | None:
        """The newest finite value of a streamed column (None when there is none)."""
        if not self.buffer.n:
            return None
        v = self.buffer.column(column)[-50:]
        v = v[np.isfinite(v)]
        return float(v[-1]) if v.size else None

    def _not_live_after_loss(self, reason: str) -> None:
        """Rows recorded after the driver went silent carry its last frame (the current it
        last measured): shown as gaps, not as live values."""
        import re

        m = re.search(r"lost for ([\d.]+) s", reason)
        silent_s = float(m.group(1)) if m else LOSS_GRACE_S
        if not self.buffer.n:
            return
        t = self.buffer.column("t_s")
        cut = t[-1] - silent_s * max(self._time_scale, 1.0)
        i = self.buffer.index_of(0)
        after = np.nonzero(t[i:] > cut)[0] + i
        for name in ("current_A", "position_mm", "temperature_est_C", "current_set_A"):
            self.buffer.column(name)[after] = np.nan
        self.loop_plot.reset()
        self.time_plots.reset()

    def _device_lost(self, text: str, reason: str = "") -> None:
        """A device is gone: the state, every readout, the health line and the message say so
        at once; a session's rows after the loss are not drawn as live. A running session is
        ended by the runtime (its driver is silent); its end report, when it comes within
        ``DRAIN_S``, names the saved folder."""
        in_session = self.session_folder is not None
        self.status = {}
        self.pending_start = None
        self._plan_s = None
        self.readouts.freeze("device lost", time.monotonic(), gone=True,
                             temperature_c=self._newest("temperature_est_C"))
        self.times.setText("elapsed –   remaining –   device lost")
        self.fire("lost")
        if self.state != State.ESTOPPED:
            self.say(text, error=True)
        if in_session and not reason:  # the end report is still to come
            self._drain_until = time.monotonic() + DRAIN_S
            self._not_live_after_loss("")
        else:
            if reason:
                self._not_live_after_loss(reason)
            self.session_folder = None
            self._drop_link()
        self._apply_state()

    def _lose(self, text: str) -> None:
        """The runtime is gone: message, link closed, buttons back to Connect."""
        self._drop_link()
        self.status = {}
        self.pending_start = None
        self.readouts.freeze("bench program stopped", time.monotonic(), gone=True)
        self.times.setText("elapsed –   remaining –")
        self.fire("lost")
        self.say(text, error=True)

    def _on_runtime_gone(self, payload: dict[str, Any]) -> None:
        if self.state == State.CONNECTING:
            reason = self.last_error or words.plain_connect(payload.get("reason", ""))
            self.link = None
            self.fire("connect_failed")
            self.say(f"Could not connect: {reason}", error=True)
            return
        folder = self.session_folder
        if self.state == State.ERROR:  # lost before: the runtime closed after it
            if folder is not None:
                self._close_aborted(folder)
                self.session_folder = None
            self._drop_link()
            return
        if folder is not None:
            self._close_aborted(folder)
            self.session_folder = None
            self.last_end = {"status": "aborted", "reason": "runtime process exited",
                             "folder": str(folder)}  # fmt: skip
            self.session_ended.emit(self.last_end)
        text = words.RUNTIME_DIED
        if folder is not None:
            text += f" The session in {folder} is marked aborted."
        self._lose(text)
        self.refresh_sessions()

    def _close_aborted(self, folder: Path) -> None:
        """Mark a session the dead runtime left 'running' as aborted (session.json only)."""
        import json

        from smabench.sessions import write_meta

        path = folder / "session.json"
        try:
            meta = json.loads(path.read_text(encoding="utf-8"))
            if meta.get("status") == "running":
                meta.update(status="aborted", end_reason="the bench program stopped")
                write_meta(folder, meta)
        except (OSError, ValueError) as exc:
            log.warning("could not mark %s aborted: %s", folder, exc)

    def say(self, text: str, error: bool = False) -> None:
        """The message line (plain words only)."""
        if error:
            self.last_error = text
            log.warning("%s", text)
        self._refused_for_fields = False
        self.message.setText(text)
        self.message.setStyleSheet("color: #c62828; font-weight: bold;" if error else "")

    def _fields_edited(self) -> None:
        """A start refused for its fields: the message follows the fields (the list shrinks as
        they are fixed, and goes when none is left)."""
        if not self._refused_for_fields:
            return
        errors = self.field_errors()
        if errors:
            self.message.setText(f"Not started: {'; '.join(errors)}.")
        else:
            self.say("All fields valid: press Start.")

    def restore_defaults(self) -> None:
        """Every setting back to the schema's default (the connection kept)."""
        self.remembered.defaults()
        self.say("Settings back to their defaults.")

    def show_error(self, text: str) -> None:
        self.say(words.plain(text), error=True)

    # ------------------------------------------------------------------ closing
    def closeEvent(self, event: QtGui.QCloseEvent) -> None:  # noqa: N802 (Qt name)
        self.timer.stop()
        self.guard.remove()
        if self.link is not None:
            self.link.estop()
        self.remembered.save()
        self.disconnect_devices()
        for t in self._closing:  # the runtime (and its mock) gone before the window is
            t.join(15.0)
        self.jobs.close()
        self.collector.stop()
        super().closeEvent(event)
