"""The identification flight flown by Betaflight's SITL on the twin, kept as Betaflight's blackbox.

The manoeuvre is `identify_flight`'s (collective steps, then per axis a doublet and a chirp),
sent as RC sticks to Betaflight 4.6 flying its own PID on the ball-joint rig (`sitl.betaflight`,
`fly_script`); Betaflight logs the flight itself (`sitl.betaflight_blackbox`). The log is
written on the SITL's clock, which is not the twin's (wall time scaled by the packets' rate,
`sim_bridge.betaflight_link`): `clock_ratio` measures it from the log, the setpoint changes
against the ticks the excitation made them on.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from fcemu.evaluation.identify_blackbox import decode_blackbox
from fcemu.evaluation.identify_flight import _Excitation, excitation
from fcemu.sim_bridge.airframe import Airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sim_bridge.twin import Twin
from fcemu.sitl.betaflight import BetaflightFlight
from fcemu.sitl.betaflight_process import BetaflightError
from fcemu.sitl.betaflight_rc import RcMap
from fcemu.sitl.traces import Traces

SPEED = 0.25  # the twin against wall time: the SITL's clock keeps closer to the twin's slower
RATE_HZ = 1000.0


def fly_identification_betaflight(airframe: Airframe, blackbox: str | Path, run_dir: str | Path | None = None,
                                  speed: float = SPEED, axis_s: float = 6.0) -> Traces:
    """Fly the identification flight with Betaflight on `airframe`'s twin; its blackbox is written to
    `blackbox`. The traces are the twin's side (the gyro sent, the motors answered), on its clock."""
    hover = airframe_spec(airframe).hover_throttle
    rates, throttle = excitation(RATE_HZ, hover, axis_s)
    run_dir = Path(run_dir) if run_dir else Path(tempfile.mkdtemp(prefix="fcemu_betaflight_identify_"))
    twin = Twin(airframe, rig="rig", dt=1.0 / RATE_HZ)
    with BetaflightFlight(run_dir, twin, RcMap(), speed=speed, blackbox=blackbox) as flight:
        traces = flight.fly_script(_Excitation(rates, throttle, round(1e6 / RATE_HZ)), len(rates) / RATE_HZ)
    if flight.blackbox_logs == 0:
        raise BetaflightError(f"Betaflight wrote no blackbox log in {run_dir} (see {run_dir / 'sitl.log'})")
    return traces


def clock_ratio(blackbox: str | Path, axis_s: float = 6.0) -> float:
    """The log's seconds per twin second over the flight: from the excitation's first tick (the
    throttle leaves the arming position) to the start of the yaw doublet, as the log shows them
    against the ticks the excitation flew them on."""
    names, table, _, _ = decode_blackbox(Path(blackbox))
    rates, _ = excitation(RATE_HZ, 0.5, axis_s)
    t = table[:, names.index("time")] * 1e-6
    yaw_start = np.flatnonzero(rates[:, 2] != 0.0)[0] / RATE_HZ
    mixer = table[:, names.index("setpoint[3]")]
    yaw = table[:, names.index("setpoint[2]")]
    started = np.flatnonzero(mixer != mixer[0])
    yawing = np.flatnonzero(np.abs(yaw) > 0)
    if not len(started) or not len(yawing):
        raise BetaflightError(f"{blackbox}: the identification flight's setpoints are not in the log")
    return float((t[yawing[0]] - t[started[0]]) / yaw_start)
