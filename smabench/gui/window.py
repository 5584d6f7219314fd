"""The operator's main window: connection, experiment and controller panels, E-STOP, live plots,
sessions.

The bench runtime runs in its own process (:class:`~smabench.gui.link.RuntimeLink`); this window
only sends commands and draws what the runtime streams, from a 30 Hz timer. If the window freezes,
the loop does not notice; if it dies, the runtime sees its pipe close and e-stops.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from smabench.gui.link import RuntimeLink, SampleBuffer
from smabench.gui.plots import LoopPlot, TimePlots
from smabench.protocols import PROTOCOL_NAMES, REFERENCE_NAMES

log = logging.getLogger(__name__)

FRAME_MS = 33
MODES = (("open_loop", "Open loop"), ("pid", "PID"), ("ff", "FF"), ("ffpid", "FF+PID"))
MODELS = ("1", "2", "sigmoid", "preisach")


def _spin(lo: float, hi: float, value: float, step: float, decimals: int = 2,
          suffix: str = "") -> QtWidgets.QDoubleSpinBox:  # fmt: skip
    w = QtWidgets.QDoubleSpinBox()
    w.setRange(lo, hi)
    w.setDecimals(decimals)
    w.setSingleStep(step)
    w.setValue(value)
    if suffix:
        w.setSuffix(" " + suffix)
    return w


class MainWindow(QtWidgets.QMainWindow):
    """Everything the operator needs at the bench."""

    session_ended = QtCore.Signal(dict)

    def __init__(self, sessions_dir: str | Path = "sessions", mock_speed: float = 1.0) -> None:
        super().__init__()
        self.setWindowTitle("smabench")
        self.sessions_dir = Path(sessions_dir)
        self.link: RuntimeLink | None = None
        self.link_load_kg: float | None = None
        self.buffer = SampleBuffer()
        self.status: dict[str, Any] = {}
        self.last_end: dict[str, Any] | None = None
        self.last_error = ""
        self.frame_times_s: list[float] = []
        self.custom_gains: list[float] | None = None  # None: the per-load gain table
        self._build(mock_speed)
        self.timer = QtCore.QTimer(self)
        self.timer.timeout.connect(self.on_frame)
        self.timer.start(FRAME_MS)
        self.refresh_sessions()
        self._set_running(False)

    # ------------------------------------------------------------------ layout
    def _build(self, mock_speed: float) -> None:
        self.estop_button = QtWidgets.QPushButton("E-STOP  (Esc)")
        self.estop_button.setMinimumHeight(70)
        self.estop_button.setStyleSheet(
            "QPushButton { background: #c62828; color: white; font-size: 22px; font-weight: bold;"
            " border-radius: 8px; } QPushButton:pressed { background: #8e0000; }"
        )
        self.estop_button.clicked.connect(self.estop)
        for key in ("Escape", "Ctrl+E", "F12"):
            sc = QtGui.QShortcut(QtGui.QKeySequence(key), self)
            sc.setContext(QtCore.Qt.ShortcutContext.ApplicationShortcut)
            sc.activated.connect(self.estop)

        left = QtWidgets.QWidget()
        lv = QtWidgets.QVBoxLayout(left)
        lv.addWidget(self.estop_button)
        lv.addWidget(self._connection_panel(mock_speed))
        lv.addWidget(self._experiment_panel())
        lv.addWidget(self._controller_panel())
        lv.addStretch(1)
        scroll = QtWidgets.QScrollArea()
        scroll.setWidget(left)
        scroll.setWidgetResizable(True)
        scroll.setMinimumWidth(340)

        self.loop_plot = LoopPlot()
        self.time_plots = TimePlots()
        live = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        live.addWidget(self.loop_plot)
        live.addWidget(self.time_plots)
        live.setSizes([500, 400])
        self.tabs = QtWidgets.QTabWidget()
        self.tabs.addTab(live, "Live")
        self.tabs.addTab(self._sessions_panel(), "Sessions")

        split = QtWidgets.QSplitter()
        split.addWidget(scroll)
        split.addWidget(self.tabs)
        split.setStretchFactor(1, 1)
        self.setCentralWidget(split)
        self.health = QtWidgets.QLabel("not connected")
        self.statusBar().addPermanentWidget(self.health)
        self.resize(1400, 900)

    def _connection_panel(self, mock_speed: float) -> QtWidgets.QGroupBox:
        box = QtWidgets.QGroupBox("Connection")
        form = QtWidgets.QFormLayout(box)
        self.use_mock = QtWidgets.QRadioButton("Built-in mock bench")
        self.use_real = QtWidgets.QRadioButton("Real devices")
        self.use_mock.setChecked(True)
        form.addRow(self.use_mock)
        self.mock_speed = _spin(1, 10, mock_speed, 1, 0, "×")
        self.mock_effect = QtWidgets.QLineEdit()
        self.mock_effect.setPlaceholderText("e.g. latent_heat=24000 (optional)")
        form.addRow("speed", self.mock_speed)
        form.addRow("plant effect", self.mock_effect)
        form.addRow(self.use_real)
        self.serial_port = QtWidgets.QComboBox()
        self.serial_port.setEditable(True)
        refresh = QtWidgets.QPushButton("↻")
        refresh.setMaximumWidth(30)
        refresh.clicked.connect(self.refresh_ports)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.serial_port, 1)
        row.addWidget(refresh)
        form.addRow("driver port", row)
        self.sensor_kind = QtWidgets.QComboBox()
        self.sensor_kind.addItems(["TCP", "RTU"])
        self.sensor_host = QtWidgets.QLineEdit("192.168.0.10")
        self.sensor_tcp_port = QtWidgets.QSpinBox()
        self.sensor_tcp_port.setRange(1, 65535)
        self.sensor_tcp_port.setValue(502)
        self.sensor_rtu_port = QtWidgets.QComboBox()
        self.sensor_rtu_port.setEditable(True)
        self.sensor_baud = QtWidgets.QComboBox()
        self.sensor_baud.addItems(["9600", "19200", "38400", "57600", "115200"])
        self.sensor_baud.setCurrentText("115200")
        self.sensor_unit = QtWidgets.QSpinBox()
        self.sensor_unit.setRange(1, 247)
        self.sensor_map = QtWidgets.QComboBox()
        from smabench.drivers.displacement import available_maps

        self.sensor_map.addItems(available_maps())
        self.sensor_map.setCurrentText("generic-rs485-laser")
        form.addRow("sensor", self.sensor_kind)
        form.addRow("TCP host", self.sensor_host)
        form.addRow("TCP port", self.sensor_tcp_port)
        form.addRow("RTU port", self.sensor_rtu_port)
        form.addRow("RTU baud", self.sensor_baud)
        form.addRow("unit id", self.sensor_unit)
        form.addRow("register map", self.sensor_map)
        self.connect_button = QtWidgets.QPushButton("Connect")
        self.connect_button.clicked.connect(self.toggle_connection)
        form.addRow(self.connect_button)
        self.refresh_ports()
        return box

    def _experiment_panel(self) -> QtWidgets.QGroupBox:
        box = QtWidgets.QGroupBox("Experiment")
        form = QtWidgets.QFormLayout(box)
        self.load_kg = _spin(0.1, 10, 2.0, 0.5, 2, "kg")
        self.protocol = QtWidgets.QComboBox()
        self.protocol.addItems(PROTOCOL_NAMES)
        self.cycles = QtWidgets.QSpinBox()
        self.cycles.setRange(1, 10000)
        self.cycles.setValue(3)
        self.current_a = _spin(0, 2.0, 1.4, 0.1, 2, "A")
        self.heat_s = _spin(0.1, 600, 3.0, 0.5, 1, "s")
        self.cool_s = _spin(0.5, 3600, 15.0, 1, 1, "s")
        self.partial_cool_s = _spin(0.1, 600, 2.0, 0.5, 1, "s")
        self.inner_heat_s = _spin(0.05, 60, 0.4, 0.1, 2, "s")
        self.inner_cool_s = _spin(0.05, 60, 0.8, 0.1, 2, "s")
        # position references (step, staircase, sine, triangle) under a closed-loop law
        self.amplitude_mm = _spin(0.05, 5, 0.8, 0.1, 2, "mm")
        self.offset_mm = _spin(-0.01, 60, -0.01, 0.1, 2, "mm")
        self.offset_mm.setSpecialValueText("middle of the stroke")
        self.period_s = _spin(1, 3600, 20, 1, 1, "s")
        for label, w in (("load", self.load_kg), ("protocol", self.protocol),
                         ("cycles", self.cycles), ("current", self.current_a),
                         ("heat time", self.heat_s), ("max cool time", self.cool_s),
                         ("incomplete: cool", self.partial_cool_s),
                         ("inner: heat", self.inner_heat_s),
                         ("inner: cool", self.inner_cool_s),
                         ("reference amplitude", self.amplitude_mm),
                         ("reference offset", self.offset_mm),
                         ("reference period", self.period_s)):  # fmt: skip
            form.addRow(label, w)
        buttons = QtWidgets.QHBoxLayout()
        self.start_button = QtWidgets.QPushButton("Start")
        self.pause_button = QtWidgets.QPushButton("Pause")
        self.pause_button.setCheckable(True)
        self.stop_button = QtWidgets.QPushButton("Stop")
        self.start_button.clicked.connect(self.start_experiment)
        self.pause_button.toggled.connect(self.pause_experiment)
        self.stop_button.clicked.connect(self.stop_experiment)
        for b in (self.start_button, self.pause_button, self.stop_button):
            buttons.addWidget(b)
        form.addRow(buttons)
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        form.addRow(self.progress)
        self.times = QtWidgets.QLabel("elapsed –   remaining –")
        form.addRow(self.times)
        self.end_label = QtWidgets.QLabel("")
        self.end_label.setWordWrap(True)
        form.addRow(self.end_label)
        return box

    def _controller_panel(self) -> QtWidgets.QGroupBox:
        box = QtWidgets.QGroupBox("Controller")
        form = QtWidgets.QFormLayout(box)
        row = QtWidgets.QHBoxLayout()
        self.mode_buttons: dict[str, QtWidgets.QRadioButton] = {}
        group = QtWidgets.QButtonGroup(box)
        for mode, label in MODES:
            b = QtWidgets.QRadioButton(label)
            group.addButton(b)
            row.addWidget(b)
            self.mode_buttons[mode] = b
            b.clicked.connect(lambda _=False, m=mode: self.set_mode(m))
        self.mode_buttons["open_loop"].setChecked(True)
        form.addRow(row)
        from smabench.control import gains_for_load

        g = gains_for_load(self.load_kg.value())
        self.kp = _spin(0, 100, g.kp, 0.01, 3)
        self.ki = _spin(0, 100, g.ki, 0.01, 3)
        self.kd = _spin(0, 100, g.kd, 0.01, 3)
        self.load_kg.valueChanged.connect(self._show_load_gains)
        form.addRow("Kp (W/mm)", self.kp)
        form.addRow("Ki (W/(mm·s))", self.ki)
        form.addRow("Kd (W·s/mm)", self.kd)
        apply = QtWidgets.QPushButton("Apply gains (default: per-load table)")
        apply.clicked.connect(self.apply_gains)
        form.addRow(apply)
        self.setpoint_label = QtWidgets.QLabel("setpoint –")
        form.addRow(self.setpoint_label)
        return box

    def _sessions_panel(self) -> QtWidgets.QWidget:
        w = QtWidgets.QWidget()
        v = QtWidgets.QVBoxLayout(w)
        self.session_list = QtWidgets.QListWidget()
        v.addWidget(self.session_list, 1)
        row = QtWidgets.QHBoxLayout()
        for label, slot in (("Refresh", self.refresh_sessions), ("Open", self.open_selected),
                            ("Export CSV…", self.export_dialog)):  # fmt: skip
            b = QtWidgets.QPushButton(label)
            b.clicked.connect(slot)
            row.addWidget(b)
        row.addStretch(1)
        row.addWidget(QtWidgets.QLabel("model"))
        self.fit_model = QtWidgets.QComboBox()
        self.fit_model.addItems(MODELS)
        self.fit_model.setCurrentText("sigmoid")
        row.addWidget(self.fit_model)
        row.addWidget(QtWidgets.QLabel("cycle (−1 = last)"))
        self.fit_cycle = QtWidgets.QSpinBox()
        self.fit_cycle.setRange(-1, 100000)
        self.fit_cycle.setValue(-1)
        row.addWidget(self.fit_cycle)
        fit = QtWidgets.QPushButton("Fit")
        fit.clicked.connect(self.fit_shown)
        row.addWidget(fit)
        v.addLayout(row)
        self.fit_text = QtWidgets.QPlainTextEdit()
        self.fit_text.setReadOnly(True)
        self.fit_text.setMaximumHeight(200)
        v.addWidget(self.fit_text)
        return w

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
        if self.use_mock.isChecked():
            args = ["--load-kg", f"{self.load_kg.value():g}", "--speed",
                    f"{self.mock_speed.value():g}"]  # fmt: skip
            for effect in filter(None, (e.strip() for e in self.mock_effect.text().split(","))):
                args += ["--effect", effect]
            return {"mock": args, "time_scale": self.mock_speed.value()}
        if self.sensor_kind.currentText() == "TCP":
            spec = f"tcp:{self.sensor_host.text().strip()}:{self.sensor_tcp_port.value()}"
        else:
            device = self.sensor_rtu_port.currentText().strip()
            spec = f"rtu:{device}:{self.sensor_baud.currentText()}"
        port = self.serial_port.currentText().strip()
        if not port:
            raise ValueError("choose the current driver's serial port")
        return {"port": port, "sensor": spec, "sensor_map": self.sensor_map.currentText(),
                "unit_id": self.sensor_unit.value()}  # fmt: skip

    def connect_devices(self) -> None:
        self.disconnect_devices()
        try:
            cfg = self.devices_config()
        except ValueError as exc:
            self.show_error(str(exc))
            return
        self.link = RuntimeLink(cfg)
        self.link_load_kg = self.load_kg.value() if "mock" in cfg else None
        self.health.setText("connecting …")
        self.connect_button.setText("Disconnect")

    def disconnect_devices(self) -> None:
        if self.link is not None:
            self.link.close()
            self.link = None
        self.status = {}
        self.connect_button.setText("Connect")
        self.health.setText("not connected")
        self._set_running(False)

    def toggle_connection(self) -> None:
        if self.link is not None:
            self.disconnect_devices()
        else:
            self.connect_devices()

    @property
    def connected(self) -> bool:
        return self.link is not None and self.link.alive and self.link.ports is not None

    # ------------------------------------------------------------------ experiment
    def selected_mode(self) -> str:
        return next((m for m, b in self.mode_buttons.items() if b.isChecked()), "open_loop")

    def settings_dict(self) -> dict[str, Any]:
        """The session's settings; a closed-loop law with a position reference when one of
        PID, FF, FF+PID is selected and the protocol is a reference."""
        mode = self.selected_mode()
        closed = mode != "open_loop" and self.protocol.currentText() in REFERENCE_NAMES
        offset = self.offset_mm.value()
        out = {
            "load_kg": self.load_kg.value(),
            "out_dir": str(self.sessions_dir),
            "time_scale": self.mock_speed.value() if self.use_mock.isChecked() else 1.0,
            "protocol": {
                "name": self.protocol.currentText(),
                "cycles": self.cycles.value(),
                "current_a": self.current_a.value(),
                "heat_s": self.heat_s.value(),
                "cool_timeout_s": self.cool_s.value(),
                "partial_cool_s": self.partial_cool_s.value(),
                "inner_heat_s": self.inner_heat_s.value(),
                "inner_cool_s": self.inner_cool_s.value(),
                "amplitude_mm": self.amplitude_mm.value(),
                "offset_mm": None if offset <= self.offset_mm.minimum() else offset,
                "period_s": self.period_s.value(),
            },
        }
        if closed:
            out["controller"] = {"mode": mode, "gains": self.custom_gains}
        return out

    def start_experiment(self) -> None:
        """Start a session (connecting first, or reconnecting a mock whose load changed)."""
        mock = self.use_mock.isChecked()
        if self.link is None or (mock and self.link_load_kg != self.load_kg.value()):
            self.connect_devices()
        if not self.wait_connected(20.0):
            return
        self.buffer.clear()
        self.loop_plot.reset()
        self.time_plots.reset()
        self.time_plots.follow = True
        self.last_end = None
        self.end_label.setText("")
        self.pause_button.setChecked(False)
        settings = self.settings_dict()
        if "controller" not in settings:
            self.mode_buttons["open_loop"].setChecked(True)
        self.link.start(settings)
        self._set_running(True)

    def wait_connected(self, timeout_s: float) -> bool:
        """Process events until the runtime reports its ports (or fails)."""
        deadline = time.monotonic() + timeout_s
        while self.link is not None and self.link.ports is None:
            QtWidgets.QApplication.processEvents(QtCore.QEventLoop.ProcessEventsFlag.AllEvents, 50)
            self.on_frame()
            if time.monotonic() > deadline:
                self.show_error("the devices did not answer in time")
                self.disconnect_devices()
                return False
        return self.link is not None

    def pause_experiment(self, on: bool) -> None:
        if self.link is not None and self.link.alive:
            self.link.send("pause" if on else "resume")
            self.pause_button.setText("Resume" if on else "Pause")

    def stop_experiment(self) -> None:
        if self.link is not None and self.link.alive:
            self.link.send("stop")

    def estop(self) -> None:
        """Both devices safe at once: the runtime e-stops (or makes the driver safe if idle)."""
        self.estop_time = time.monotonic()
        if self.link is not None:
            self.link.estop()
        self.statusBar().showMessage("E-STOP: output off", 10000)

    def set_mode(self, mode: str) -> None:
        if self.link is not None and self.link.alive:
            self.link.send(f"mode {mode}")

    def _show_load_gains(self, load_kg: float) -> None:
        """Show the PID gains of the per-load table for this load (until gains are applied)."""
        if self.custom_gains is None:
            from smabench.control import gains_for_load

            g = gains_for_load(load_kg)
            for spin, v in ((self.kp, g.kp), (self.ki, g.ki), (self.kd, g.kd)):
                spin.setValue(v)

    def apply_gains(self) -> None:
        """Use these gains from now on (live when running; for the next session anyway)."""
        self.custom_gains = [self.kp.value(), self.ki.value(), self.kd.value()]
        if self.link is not None and self.link.alive and self.running:
            self.link.send("gains " + " ".join(map(str, self.custom_gains)))

    def _set_running(self, running: bool) -> None:
        self.running = running
        self.start_button.setEnabled(not running)
        self.pause_button.setEnabled(running)
        self.stop_button.setEnabled(running)

    # ------------------------------------------------------------------ frame
    def on_frame(self) -> None:
        t0 = time.perf_counter()
        link = self.link
        if link is not None:
            rows = link.take_rows()
            if rows.size:
                self.buffer.append_rows(rows)
            for kind, payload in link.poll():
                self.on_event(kind, payload)
        if self.tabs.currentIndex() == 0 or self.buffer.n:
            self.loop_plot.update_from(self.buffer)
            self.time_plots.update_from(self.buffer)
        if self.buffer.n:
            sp = self.buffer.column("setpoint_mm")[-1]
            self.setpoint_label.setText(
                "setpoint –" if not np.isfinite(sp) else f"setpoint {sp:.3f} mm"
            )
        self.frame_times_s.append(time.perf_counter() - t0)
        del self.frame_times_s[:-1000]

    def on_event(self, kind: str, payload: dict[str, Any]) -> None:
        if kind == "P":
            self.link.ports = payload
            dev = payload["device"]
            self.statusBar().showMessage(f"connected: {dev['name']} on {payload['driver']}, "
                                         f"sensor {payload['sensor']}", 5000)  # fmt: skip
        elif kind == "S":
            if "error" in payload:
                self.show_error(payload["error"])
                return
            self.status = payload
            self._show_status(payload)
        elif kind == "E":
            self.last_end = payload
            self._set_running(False)
            if payload["status"] == "completed":
                self.progress.setValue(1000)
            el = float(self.status.get("elapsed_s", 0.0))
            self.times.setText(f"elapsed {el:.0f} s   ended: {payload['status']}")
            text = f"{payload['status']}: {payload['reason']}"
            if payload.get("samples") is not None:
                text += f" ({payload['samples']} samples)"
            self.end_label.setText(text)
            if payload["status"] != "completed":
                self.show_error(f"session {text}")
            self.refresh_sessions()
            self.session_ended.emit(payload)
        elif kind == "Q":
            if self.link is not None and self.link.ports is None:
                self.show_error(f"could not connect: {payload.get('reason', '')}")
            self.link = None
            self.connect_button.setText("Connect")
            self.health.setText("not connected")
            self._set_running(False)

    def _show_status(self, st: dict[str, Any]) -> None:
        stats = st.get("sensor_stats", {})
        drv = "ok" if st.get("driver_link_ok") else "LOST"
        fault = f" ({st['driver_fault']})" if st.get("driver_fault") else ""
        self.health.setText(
            f"driver {drv}{fault} · sensor {stats.get('ok', 0)}/{stats.get('reads', 0)} ok, "
            f"{stats.get('timeouts', 0)} timeouts"
        )
        self.health.setStyleSheet("" if drv == "ok" and not fault else "color: #c62828;")
        if "progress" in st and st.get("running"):
            p = float(st["progress"])
            self.progress.setValue(int(1000 * p))
            el = float(st.get("elapsed_s", 0.0))
            rem = f"{el / p * (1 - p):.0f} s" if p > 0.02 else "–"
            self.times.setText(f"elapsed {el:.0f} s   remaining {rem}   "
                               f"cycle {st['cycle'] + 1}/{st['cycles']} {st['phase']}")  # fmt: skip

    def show_error(self, text: str) -> None:
        self.last_error = text
        self.statusBar().showMessage(text, 15000)
        log.warning("%s", text)

    # ------------------------------------------------------------------ sessions
    def refresh_sessions(self) -> None:
        self.session_list.clear()
        if not self.sessions_dir.is_dir():
            return
        folders = sorted((p for p in self.sessions_dir.iterdir() if (p / "session.json").is_file()),
                         key=lambda p: p.stat().st_mtime, reverse=True)  # fmt: skip
        for folder in folders:
            item = QtWidgets.QListWidgetItem(folder.name)
            item.setData(QtCore.Qt.ItemDataRole.UserRole, str(folder))
            self.session_list.addItem(item)

    def selected_session(self) -> Path | None:
        item = self.session_list.currentItem()
        return Path(item.data(QtCore.Qt.ItemDataRole.UserRole)) if item else None

    def open_session(self, folder: str | Path) -> None:
        """Replay a recorded session in the plots."""
        from smabench.sessions import load_session

        try:
            s = load_session(folder)
        except ValueError as exc:
            self.show_error(str(exc))
            return
        cols = {c: s.data[c] for c in s.data if c != "mode"}
        if "temperature_est_C" not in cols and "temperature_C" in cols:
            cols["temperature_est_C"] = cols["temperature_C"]
        if "t_s" not in cols:
            cols["t_s"] = np.arange(len(s), dtype=float)
        cols.setdefault("cycle", np.zeros(len(s)))
        self.buffer.clear()
        self.loop_plot.reset()
        self.time_plots.reset()
        self.buffer.append_columns(cols)
        self.time_plots.follow = False
        self.loop_plot.update_from(self.buffer)
        self.time_plots.update_from(self.buffer)
        self.time_plots.show_all()
        self.loop_plot.autoRange()
        self.opened = Path(folder)
        self.statusBar().showMessage(f"opened {Path(folder).name}: {len(s)} samples", 5000)

    def open_selected(self) -> None:
        folder = self.selected_session()
        if folder is not None:
            self.open_session(folder)
            self.tabs.setCurrentIndex(0)

    def export_session(self, folder: str | Path, out: str | Path) -> int:
        from smabench.sessions import export_csv, load_session

        n = export_csv(load_session(folder), out)
        self.statusBar().showMessage(f"{n} rows written to {out}", 5000)
        return n

    def export_dialog(self) -> None:
        folder = self.selected_session()
        if folder is None:
            self.show_error("choose a session to export")
            return
        out, _ = QtWidgets.QFileDialog.getSaveFileName(
            self, "Export CSV", str(folder.with_suffix(".csv")), "CSV (*.csv)"
        )
        if out:
            try:
                self.export_session(folder, out)
            except (ValueError, OSError) as exc:
                self.show_error(str(exc))

    def fit_shown(self) -> dict[str, float] | None:
        """Fit the chosen model to the chosen cycle of what the plots show; returns the figures."""
        from smabench.physics.identify import FitError, fit_loop

        if self.buffer.n == 0:
            self.show_error("nothing to fit: open a session or run one")
            return None
        cycle = self.buffer.column("cycle")
        want = self.fit_cycle.value()
        finite_cycles = cycle[np.isfinite(cycle)]
        chosen = float(finite_cycles.max()) if want < 0 and finite_cycles.size else float(want)
        sel = cycle == chosen if np.isfinite(cycle).any() else np.ones(self.buffer.n, bool)
        temp = self.buffer.column("temperature_est_C")[sel]
        pos = self.buffer.column("position_mm")[sel]
        ok = np.isfinite(temp) & np.isfinite(pos)
        try:
            fit = fit_loop(temp[ok], pos[ok], self.fit_model.currentText())
        except (FitError, ValueError) as exc:
            self.fit_text.setPlainText(f"fit failed: {exc}")
            return None
        self.loop_plot.show_model(temp[ok], fit.predict(temp[ok]))
        lines = [f"model {fit.model} on cycle {chosen:.0f} ({fit.n_points} points)",
                 f"rmse {fit.rmse_mm:.4f} mm   nrmse {fit.nrmse_percent:.3f} % of stroke   "
                 f"ard {fit.ard_percent:.3f} %"]  # fmt: skip
        lines += [f"  {k} = {v:.6g}" for k, v in fit.parameters.items()]
        self.fit_text.setPlainText("\n".join(lines))
        return {"nrmse_percent": fit.nrmse_percent, "rmse_mm": fit.rmse_mm}

    # ------------------------------------------------------------------ closing
    def closeEvent(self, event: QtGui.QCloseEvent) -> None:  # noqa: N802 (Qt name)
        self.timer.stop()
        self.disconnect_devices()
        super().closeEvent(event)
