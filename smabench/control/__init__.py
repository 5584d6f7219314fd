"""Position control of the SMA wire: PID, feed-forward (inverse loop model + inverse heat
balance), FF+PID, online model adaptation, references and live bumpless switching."""

from smabench.control.controller import MODES, Controller, parse_switch
from smabench.control.factory import ControllerSettings, build_controller
from smabench.control.pid import PID, PIDGains, gains_for_load

__all__ = [
    "MODES",
    "PID",
    "Controller",
    "ControllerSettings",
    "PIDGains",
    "build_controller",
    "gains_for_load",
    "parse_switch",
]
