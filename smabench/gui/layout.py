"""The operator window's layout (a mixin of :class:`~smabench.gui.window.MainWindow`): the run
bar that never scrolls, the settings tabs built from the settings schema, the plots and the
sessions tab; and which fields are on screen for the chosen protocol, law and device kind."""

from __future__ import annotations

from typing import Any

from PySide6 import QtCore, QtGui, QtWidgets

from smabench import settings as schema
from smabench.gui import words
from smabench.gui.estop import KEY_NAMES
from smabench.gui.fields import Field, NoWheelCombo, ValueField, label_for, make_field
from smabench.gui.plots import LoopPlot, SelfSensePlots, TimePlots
from smabench.gui.sessions_view import ReplayView
from smabench.gui.specs import (
    CONNECTION,
    FIT_CYCLE,
    OPEN_LOOP_CURRENT,
    SELFSENSE_KEYS,
    mode_uses,
    shown,
)
from smabench.gui.state import IN_SESSION
from smabench.gui.trends import TrendPlots
from smabench.settings import GAIN_SETS, PROTOCOL_NAMES, Setting

MODES = (("open_loop", "Open loop"), ("pid", "PID"), ("ff", "FF"), ("ffpid", "FF+PID"))
MODELS = ("1", "2", "sigmoid", "preisach")
MOCK_RESISTIVITY = (("plant's two-phase", ""), ("flexinol", "flexinol"),
                    ("flexinol-rphase", "flexinol-rphase"))  # fmt: skip
"""The mock's wire-resistance models (``smabench mock --resistivity``): label, value."""
BANNER_HEIGHT = 40  # px, reserved whether the banner shows or not
MESSAGE_HEIGHT = 36  # px: two lines


class WindowLayout:
    """Builds the widgets; the window's state and behaviour live in ``MainWindow``."""

    # ------------------------------------------------------------------ layout
    def _field(self, setting: Setting) -> Field:
        w = make_field(setting)
        self.fields[setting.key] = w
        return w

    def _build(self, mock_speed: float) -> None:
        central = QtWidgets.QWidget()
        outer = QtWidgets.QVBoxLayout(central)
        outer.setContentsMargins(6, 6, 6, 6)
        outer.setSpacing(4)
        outer.addWidget(self._run_bar())
        self.settings_tabs = QtWidgets.QTabWidget()
        for title, panel in (("Experiment", self._experiment_panel()),
                             ("Limits", self._limits_panel()),
                             ("Controller", self._controller_panel()),
                             ("Connection", self._connection_panel(mock_speed))):  # fmt: skip
            scroll = QtWidgets.QScrollArea()
            scroll.setWidget(panel)
            scroll.setWidgetResizable(True)
            scroll.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
            self.settings_tabs.addTab(scroll, title)
        self.settings_tabs.setMinimumWidth(360)
        self.loop_plot = LoopPlot()
        self.time_plots = TimePlots()
        # side by side: the three stacked time plots get the tab's whole height
        top = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        top.addWidget(self.loop_plot)
        top.addWidget(self.time_plots)
        top.setSizes([400, 600])
        # below them, only in a session with a self-sense calibration: R and the estimate
        self.selfsense_plots = SelfSensePlots(self.time_plots.p_current)
        self.selfsense_plots.setVisible(False)
        live = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        live.addWidget(top)
        live.addWidget(self.selfsense_plots)
        live.setSizes([600, 300])
        self.replay = ReplayView()
        self.tabs = QtWidgets.QTabWidget()
        self.tabs.addTab(live, "Live")
        self.tabs.addTab(self._sessions_panel(), "Sessions")
        self.tabs.addTab(self.replay, "Replay (recorded)")
        self.trend_plots = TrendPlots()
        self.tabs.addTab(self.trend_plots, "Trends (per cycle)")
        settings = QtWidgets.QWidget()
        sv = QtWidgets.QVBoxLayout(settings)
        sv.setContentsMargins(0, 0, 0, 0)
        sv.addWidget(self.settings_tabs, 1)
        self.defaults_button = QtWidgets.QPushButton("Defaults")
        self.defaults_button.setToolTip("Every setting back to its default (the connection kept; "
                                        "the entries are remembered between starts)")
        self.defaults_button.clicked.connect(self.restore_defaults)
        bottom = QtWidgets.QHBoxLayout()
        bottom.addStretch(1)
        bottom.addWidget(self.defaults_button)
        sv.addLayout(bottom)
        split = QtWidgets.QSplitter()
        split.addWidget(settings)
        split.addWidget(self.tabs)
        split.setStretchFactor(1, 1)
        split.setSizes([400, 1000])
        outer.addWidget(split, 1)
        self.setCentralWidget(central)
        self.health = QtWidgets.QLabel("not connected")
        self.statusBar().addPermanentWidget(self.health)
        self.resize(1400, 900)
        screen = QtGui.QGuiApplication.primaryScreen()
        if screen is not None:  # never larger than the screen (run controls must be in view)
            avail = screen.availableGeometry()
            if avail.width() < 1400 or avail.height() < 900:
                self.resize(min(1400, avail.width()), min(900, avail.height()))
        self._show_setting_fields()
        self._show_device_fields()

    def _run_bar(self) -> QtWidgets.QWidget:
        bar = QtWidgets.QFrame()
        bar.setFrameShape(QtWidgets.QFrame.Shape.StyledPanel)
        v = QtWidgets.QVBoxLayout(bar)
        v.setContentsMargins(6, 6, 6, 6)
        v.setSpacing(4)
        row = QtWidgets.QHBoxLayout()
        self.estop_button = QtWidgets.QPushButton(f"E-STOP\n{KEY_NAMES}")
        self.estop_button.setMinimumSize(220, 64)
        self.estop_button.setToolTip(f"Output off at once ({KEY_NAMES}, from anywhere)")
        self.estop_button.setStyleSheet(
            "QPushButton { background: #c62828; color: white; font-size: 20px; font-weight: bold;"
            " border-radius: 8px; } QPushButton:pressed { background: #8e0000; }"
        )
        self.estop_button.pressed.connect(self.estop)  # on press, not on release
        row.addWidget(self.estop_button)
        # beside the E-STOP at every width: the hand that pressed it finds it there
        self.ack_button = QtWidgets.QPushButton("Acknowledge\nE-STOP")
        self.ack_button.setMinimumSize(110, 64)
        self.ack_button.setToolTip("Release the latched E-STOP once the bench is safe")
        self.ack_button.clicked.connect(self.acknowledge_estop)
        row.addWidget(self.ack_button)
        self.state_label = QtWidgets.QLabel()
        self.state_label.setMinimumWidth(150)
        self.state_label.setStyleSheet("font-size: 15px; font-weight: bold;")
        row.addWidget(self.state_label)
        self.connect_button = QtWidgets.QPushButton("Connect")
        self.connect_button.clicked.connect(self.toggle_connection)
        self.start_button = QtWidgets.QPushButton("Start")
        self.pause_button = QtWidgets.QPushButton("Pause")
        self.stop_button = QtWidgets.QPushButton("Stop")
        self.start_button.clicked.connect(self.start_experiment)
        self.pause_button.clicked.connect(self.toggle_pause)
        self.stop_button.clicked.connect(self.stop_experiment)
        for b in (self.connect_button, self.start_button, self.pause_button, self.stop_button):
            b.setMinimumSize(92, 44)
            row.addWidget(b)
        prog = QtWidgets.QVBoxLayout()
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setMinimumWidth(180)
        self.times = QtWidgets.QLabel("elapsed –   remaining –")
        prog.addWidget(self.progress)
        prog.addWidget(self.times)
        row.addLayout(prog, 1)
        v.addLayout(row)
        # the banner's place is always there (blank when nothing is latched): nothing below it
        # moves when it appears
        self.banner = QtWidgets.QFrame()
        self.banner.setObjectName("banner")
        bl = QtWidgets.QHBoxLayout(self.banner)
        bl.setContentsMargins(8, 2, 8, 2)
        self.banner_label = QtWidgets.QLabel()
        self.banner_label.setWordWrap(True)
        bl.addWidget(self.banner_label, 1)
        self.banner.setFixedHeight(BANNER_HEIGHT)
        self.show_banner(False)
        v.addWidget(self.banner)
        msgs = QtWidgets.QHBoxLayout()
        self.message = QtWidgets.QLabel("")
        self.message.setWordWrap(True)
        self.message.setFixedHeight(MESSAGE_HEIGHT)
        self.message.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        msgs.addWidget(self.message, 3)
        # background results (fits, exports, sessions read) announce themselves here, beside
        # the message line, never in it
        self.jobs_label = QtWidgets.QLabel("")
        self.jobs_label.setWordWrap(True)
        self.jobs_label.setFixedHeight(MESSAGE_HEIGHT)
        self.jobs_label.setStyleSheet("color: #1a4f8a;")
        msgs.addWidget(self.jobs_label, 2)
        v.addLayout(msgs)
        self.readout = QtWidgets.QLabel("readouts: not connected")
        self.readout.setStyleSheet("color: #333;")
        # beside the readouts (its place is there, blank without self-sensing): where the
        # controller's position comes from, the fallback on the wire's resistance and its end
        self.sensing_label = QtWidgets.QLabel("")
        # one line that never widens the window nor moves what is below it (the tooltip has
        # the whole sentence)
        self.sensing_label.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored,
                                         QtWidgets.QSizePolicy.Policy.Preferred)  # fmt: skip
        self.sensing_label.setTextInteractionFlags(
            QtCore.Qt.TextInteractionFlag.TextSelectableByMouse
        )
        readouts = QtWidgets.QHBoxLayout()
        readouts.addWidget(self.readout, 3)
        readouts.addWidget(self.sensing_label, 2)
        v.addLayout(readouts)
        return bar

    def show_banner(self, on: bool, text: str = "") -> None:
        """The latched E-STOP banner in its reserved place (blank when ``on`` is False)."""
        self.banner_label.setText(text if on else "")
        self.banner.setStyleSheet(
            "QFrame#banner { background: %s; } QLabel { color: white; font-size: 14px; "
            "font-weight: bold; }" % ("#c62828" if on else "transparent"))  # fmt: skip

    def _form_panel(self) -> tuple[QtWidgets.QWidget, QtWidgets.QFormLayout]:
        w = QtWidgets.QWidget()
        form = QtWidgets.QFormLayout(w)
        form.setFieldGrowthPolicy(QtWidgets.QFormLayout.FieldGrowthPolicy.AllNonFixedFieldsGrow)
        return w, form

    def _add_field(self, form: QtWidgets.QFormLayout, setting: Setting) -> Field:
        w = self._field(setting)
        if setting.kind == "bool":
            form.addRow(w)
        else:
            form.addRow(label_for(setting), w)
        return w

    def _experiment_panel(self) -> QtWidgets.QWidget:
        w, form = self._form_panel()
        self.experiment_form = form
        self.protocol = NoWheelCombo()
        self.protocol.addItems(PROTOCOL_NAMES)
        self.protocol.setToolTip(words.tooltip(schema.get("protocol.name")))
        self.protocol.currentTextChanged.connect(self._show_setting_fields)
        for setting in shown("load_wire"):
            self._add_field(form, setting)
        self.load_field = self.fields["load_kg"]
        form.addRow("protocol", self.protocol)
        self.protocol_fields = [s.key for s in shown("protocol")]
        for setting in shown("protocol"):
            self._add_field(form, setting)
        for setting in shown("loop"):
            if setting.key not in SELFSENSE_KEYS:
                self._add_field(form, setting)
        self._selfsense_rows(form)
        self.load_field.changed.connect(self._show_table_gains)
        return w

    def _selfsense_rows(self, form: QtWidgets.QFormLayout) -> None:
        """Position from the wire's resistance (issue 26): the probe current, the calibration
        file (typed, or chosen with its "…" button), the fallback and the feedback (live in a
        session with a calibration)."""
        head = QtWidgets.QLabel("Position from the wire's resistance")
        head.setStyleSheet("font-weight: bold; margin-top: 6px;")
        form.addRow(head)
        by_key = {s.key: s for s in shown("loop")}
        for key in SELFSENSE_KEYS:
            setting = by_key[key]
            if key != "selfsense":
                self._add_field(form, setting)
                continue
            field = self._field(setting)
            browse = QtWidgets.QPushButton("…")  # narrow: the panel is narrow
            browse.setMaximumWidth(30)
            browse.setToolTip("Choose a calibration file (from smabench selfsense calibrate)")
            browse.clicked.connect(self.choose_selfsense_file)
            self.selfsense_row = QtWidgets.QWidget()
            row = QtWidgets.QHBoxLayout(self.selfsense_row)
            row.setContentsMargins(0, 0, 0, 0)
            row.addWidget(field, 1)
            row.addWidget(browse)
            self.selfsense_browse = browse
            form.addRow(label_for(setting), self.selfsense_row)
        self.fields["feedback"].changed.connect(self.feedback_chosen)

    def _limits_panel(self) -> QtWidgets.QWidget:
        w, form = self._form_panel()
        note = QtWidgets.QLabel("Checked every control tick; a session that crosses one stops "
                                "with the output off.")  # fmt: skip
        note.setWordWrap(True)
        form.addRow(note)
        for setting in shown("limits"):
            self._add_field(form, setting)
        return w

    def _controller_panel(self) -> QtWidgets.QWidget:
        w, form = self._form_panel()
        self.controller_form = form
        row = QtWidgets.QHBoxLayout()
        self.mode_buttons: dict[str, QtWidgets.QRadioButton] = {}
        group = QtWidgets.QButtonGroup(w)
        for mode, label in MODES:
            b = QtWidgets.QRadioButton(label)
            group.addButton(b)
            row.addWidget(b)
            self.mode_buttons[mode] = b
            b.clicked.connect(lambda _=False, m=mode: self.set_mode(m))
            b.toggled.connect(self._show_setting_fields)
        self.mode_buttons["open_loop"].setChecked(True)
        form.addRow(row)
        self.active_mode = QtWidgets.QLabel("active law: – (no session)")
        self.active_mode.setStyleSheet("font-weight: bold;")
        form.addRow(self.active_mode)
        self._add_field(form, OPEN_LOOP_CURRENT)
        self.controller_fields = [s.key for s in shown("controller")]
        for setting in shown("controller"):
            self._add_field(form, setting)
        self.gain_boxes: dict[str, QtWidgets.QGroupBox] = {}
        self.gain_table_boxes: dict[str, QtWidgets.QCheckBox] = {}
        self.gain_apply: dict[str, QtWidgets.QPushButton] = {}
        for law, gs in GAIN_SETS.items():
            box = QtWidgets.QGroupBox(f"{gs.label} gains")
            f = QtWidgets.QFormLayout(box)
            table = QtWidgets.QCheckBox("per-load table (follows the load)")
            table.setChecked(True)
            table.toggled.connect(lambda on, law=law: self.use_gain_table(law, on))
            self.gain_table_boxes[law] = table
            f.addRow(table)
            for key in gs.keys:
                setting = next(s for s in shown("gains") if s.key == key)
                fw = self._field(setting)
                short = setting.label.removeprefix(gs.label).strip()  # the box names the law
                f.addRow(f"{short} ({setting.unit})" if setting.unit else short, fw)
            apply = QtWidgets.QPushButton("Apply these gains")
            apply.clicked.connect(lambda _=False, law=law: self.apply_gains(law))
            self.gain_apply[law] = apply
            f.addRow(apply)
            self.gain_boxes[law] = box
            form.addRow(box)
        self.gain_note = QtWidgets.QLabel("Open loop has no gains: choose PID or FF+PID to see "
                                          "theirs.")  # fmt: skip
        self.gain_note.setWordWrap(True)
        form.addRow(self.gain_note)
        self.setpoint_label = QtWidgets.QLabel("setpoint –")
        form.addRow(self.setpoint_label)
        self._show_table_gains()
        return w

    def _connection_panel(self, mock_speed: float) -> QtWidgets.QWidget:
        w, form = self._form_panel()
        self.connection_form = form
        self.use_mock = QtWidgets.QRadioButton("Built-in mock bench")
        self.use_real = QtWidgets.QRadioButton("Real devices")
        self.use_mock.setChecked(True)
        self.use_mock.toggled.connect(self._show_device_fields)
        form.addRow(self.use_mock)
        form.addRow(self.use_real)
        self.mock_speed = self._add_field(form, CONNECTION["mock_speed"])
        self.mock_speed.set_value(mock_speed)
        self.mock_effect = QtWidgets.QLineEdit()
        self.mock_effect.setPlaceholderText("e.g. latent_heat=24000 (optional)")
        form.addRow("plant effect", self.mock_effect)
        self.mock_thermocouple = QtWidgets.QCheckBox("thermocouple on the wire (measured °C)")
        form.addRow(self.mock_thermocouple)
        self.mock_resistivity = NoWheelCombo()
        for label, value in MOCK_RESISTIVITY:
            self.mock_resistivity.addItem(label, value)
        self.mock_resistivity.setToolTip(
            "The mock wire's resistance: the plant's two-phase one, or a resistivity model "
            "(what the wire voltage, and so resistance sensing, sees)")
        form.addRow("wire resistance", self.mock_resistivity)
        self.serial_port = NoWheelCombo()
        self.serial_port.setEditable(True)
        refresh = QtWidgets.QPushButton("↻")
        refresh.setToolTip("look for serial ports again")
        refresh.setMaximumWidth(30)
        refresh.clicked.connect(self.refresh_ports)
        self.port_row = QtWidgets.QWidget()
        pr = QtWidgets.QHBoxLayout(self.port_row)
        pr.setContentsMargins(0, 0, 0, 0)
        pr.addWidget(self.serial_port, 1)
        pr.addWidget(refresh)
        form.addRow("driver port", self.port_row)
        self.sensor_kind = NoWheelCombo()
        self.sensor_kind.addItems(["TCP", "RTU"])
        self.sensor_kind.currentTextChanged.connect(self._show_device_fields)
        form.addRow("sensor link", self.sensor_kind)
        self.sensor_host = QtWidgets.QLineEdit("192.168.0.10")
        form.addRow("TCP host", self.sensor_host)
        self.sensor_tcp_port = self._add_field(form, CONNECTION["sensor_tcp_port"])
        self.sensor_rtu_port = NoWheelCombo()
        self.sensor_rtu_port.setEditable(True)
        form.addRow("RTU port", self.sensor_rtu_port)
        self.sensor_baud = NoWheelCombo()
        self.sensor_baud.addItems(["9600", "19200", "38400", "57600", "115200"])
        self.sensor_baud.setCurrentText("115200")
        form.addRow("RTU baud", self.sensor_baud)
        self.sensor_unit = self._add_field(form, CONNECTION["sensor_unit"])
        self.sensor_map = NoWheelCombo()
        from smabench.drivers.displacement import available_maps

        self.sensor_map.addItems(available_maps())
        self.sensor_map.setCurrentText("generic-rs485-laser")
        form.addRow("register map", self.sensor_map)
        self.refresh_ports()
        return w

    def _sessions_panel(self) -> QtWidgets.QWidget:
        w = QtWidgets.QWidget()
        v = QtWidgets.QVBoxLayout(w)
        top = QtWidgets.QHBoxLayout()
        self.sessions_label = QtWidgets.QLabel()
        self.sessions_label.setTextInteractionFlags(
            QtCore.Qt.TextInteractionFlag.TextSelectableByMouse
        )
        top.addWidget(self.sessions_label, 1)
        for label, slot in (("Change folder…", self.choose_sessions_dir),
                            ("Open a session folder…", self.open_folder_dialog),
                            ("Refresh", self.refresh_sessions)):  # fmt: skip
            b = QtWidgets.QPushButton(label)
            b.clicked.connect(slot)
            top.addWidget(b)
        v.addLayout(top)
        self.session_list = QtWidgets.QTreeWidget()
        self.session_list.setHeaderLabels(["date", "load", "protocol", "status", "folder"])
        self.session_list.setRootIsDecorated(False)
        self.session_list.setAlternatingRowColors(True)
        self.session_list.itemDoubleClicked.connect(lambda *_: self.open_selected())
        v.addWidget(self.session_list, 1)
        row = QtWidgets.QHBoxLayout()
        for label, slot in (("Open (replay)", self.open_selected),
                            ("Export CSV…", self.export_dialog)):  # fmt: skip
            b = QtWidgets.QPushButton(label)
            b.clicked.connect(slot)
            row.addWidget(b)
        row.addStretch(1)
        row.addWidget(QtWidgets.QLabel("model"))
        self.fit_model = NoWheelCombo()
        self.fit_model.addItems(MODELS)
        self.fit_model.setCurrentText("sigmoid")
        row.addWidget(self.fit_model)
        row.addWidget(QtWidgets.QLabel("cycle"))
        self.fit_cycle = ValueField(FIT_CYCLE)
        self.fit_cycle.setMaximumWidth(70)
        row.addWidget(self.fit_cycle)
        self.fit_button = QtWidgets.QPushButton("Fit selected session")
        self.fit_button.clicked.connect(self.fit_selected)
        row.addWidget(self.fit_button)
        v.addLayout(row)
        return w

    # ------------------------------------------------------------------ field visibility
    def _show_setting_fields(self, *_: Any) -> None:
        """Only what the chosen protocol and control law use is on screen."""
        if not hasattr(self, "gain_note") or not hasattr(self, "experiment_form"):
            return  # still building
        name = self.protocol.currentText()
        mode = self.selected_mode()
        live_controller = self.session_controller and self.state in IN_SESSION
        closed = mode != "open_loop" or live_controller  # mid-run: the session's protocol
        for key in self.protocol_fields:
            setting = self.fields[key].setting
            self.experiment_form.setRowVisible(self.fields[key], setting.uses(name, closed))
        for key in self.controller_fields:
            setting = self.fields[key].setting
            self.controller_form.setRowVisible(self.fields[key],
                                               closed and mode_uses(setting, mode))  # fmt: skip
        self.controller_form.setRowVisible(self.fields[OPEN_LOOP_CURRENT.key], closed)
        for law, box in self.gain_boxes.items():
            uses = (law == "pid" and mode == "pid") or (law != "pid" and mode == "ffpid")
            self.controller_form.setRowVisible(box, uses)
        self.controller_form.setRowVisible(self.gain_note, mode in ("open_loop", "ff"))
        self.gain_note.setText("Open loop has no gains: choose PID or FF+PID to see theirs."
                               if mode == "open_loop" else
                               "FF (feed-forward alone) has no feedback gains.")  # fmt: skip

    def _show_device_fields(self, *_: Any) -> None:
        mock = self.use_mock.isChecked()
        tcp = self.sensor_kind.currentText() == "TCP"
        f = self.connection_form
        f.setRowVisible(self.mock_speed, mock)
        f.setRowVisible(self.mock_effect, mock)
        f.setRowVisible(self.mock_thermocouple, mock)
        f.setRowVisible(self.mock_resistivity, mock)
        for wdg in (self.port_row, self.sensor_kind, self.sensor_unit, self.sensor_map):
            f.setRowVisible(wdg, not mock)
        for wdg in (self.sensor_host, self.sensor_tcp_port):
            f.setRowVisible(wdg, not mock and tcp)
        for wdg in (self.sensor_rtu_port, self.sensor_baud):
            f.setRowVisible(wdg, not mock and not tcp)

    def visible_fields(self) -> list[Field]:
        return [f for f in self.fields.values() if f.isVisibleTo(self)]

