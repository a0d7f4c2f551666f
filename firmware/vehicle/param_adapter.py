"""Parameters → what the vehicle and its controllers use: one typed settings record per change.

`VehicleSettings.from_params` turns the parameter table into the plain values the tick reads
(parameters change only through here, never per tick); `pid_gains` turns the PID_* and IMU_*
parameters into `PIDGains` for any `PIDRateController` the vehicle flies, and
`set_gain_defaults` does the reverse at start-up, so a ground station sees the loaded preset's
gains as the defaults.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from fcemu.firmware.controller import RateController
from fcemu.firmware.params import CONTROLLERS, ParamTable
from fcemu.firmware.pid import PIDGains
from fcemu.firmware.pid_controller import PIDRateController
from fcemu.firmware.stick_rates import ActualRates, StickRates

AXES = ("ROLL", "PITCH", "YAW")


@dataclass(frozen=True)
class VehicleSettings:
    controller: str  # CTRL_SEL by name (may name a controller that is not loaded)
    of_loss_us: float
    rc_loss_us: float
    rates: StickRates
    stab_tilt_max: float  # rad at full stick
    stab_angle_p: float  # rad/s per rad
    hover_throttle: float
    fs_hold_us: float
    fs_desc_spd: float  # m/s, down positive
    fs_desc_max_us: float

    @classmethod
    def from_params(cls, p: ParamTable) -> VehicleSettings:
        curves = []
        for a in "RPY":
            center = p[f"RATE_{a}_CENTER"]
            curves.append(ActualRates(center, max(p[f"RATE_{a}_MAX"], center), p[f"RATE_{a}_EXPO"]))
        return cls(controller=CONTROLLERS[int(p["CTRL_SEL"])], of_loss_us=p["COM_OF_LOSS_T"] * 1e6,
                   rc_loss_us=p["COM_RC_LOSS_T"] * 1e6, rates=StickRates(*curves),
                   stab_tilt_max=math.radians(p["STAB_ANGLE_MAX"]), stab_angle_p=p["STAB_ANGLE_P"],
                   hover_throttle=p["MPC_THR_HOVER"], fs_hold_us=p["FS_HOLD_T"] * 1e6,
                   fs_desc_spd=p["FS_DESC_SPD"], fs_desc_max_us=p["FS_DESC_MAX_T"] * 1e6)


def pid_gains(p: ParamTable, base: PIDGains) -> PIDGains:
    """`base` with the gains and filter cut-offs the parameters set."""
    return base.with_(kp=tuple(p[f"PID_{a}_P"] for a in AXES), ki=tuple(p[f"PID_{a}_I"] for a in AXES),
                      kd=tuple(p[f"PID_{a}_D"] for a in AXES), kff=tuple(p[f"PID_{a}_FF"] for a in AXES),
                      gyro_lowpass_hz=p["IMU_GYRO_CUTOFF"], dterm_lowpass_hz=p["IMU_DGYRO_CUTOFF"])


def set_gain_defaults(p: ParamTable, gains: PIDGains) -> None:
    """Make `gains` the defaults of the PID_* and IMU_* parameters."""
    for i, axis in enumerate(AXES):
        for key, values in (("P", gains.kp), ("I", gains.ki), ("D", gains.kd), ("FF", gains.kff)):
            p.set_default(f"PID_{axis}_{key}", values[i])
    p.set_default("IMU_GYRO_CUTOFF", gains.gyro_lowpass_hz)
    p.set_default("IMU_DGYRO_CUTOFF", gains.dterm_lowpass_hz)


def tunable_pids(controllers: Mapping[str, RateController]) -> list[PIDRateController]:
    return [c for c in controllers.values() if isinstance(c, PIDRateController)]


def apply_pid_gains(p: ParamTable, pids: list[PIDRateController]) -> None:
    for pid in pids:
        pid.set_gains(pid_gains(p, pid.gains))
