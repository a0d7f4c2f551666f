"""The vehicle as PX4 splits it: the mode state machine (modes.py), one flight task per mode
(flight_tasks.py), the land detector (land_detector.py), parameters → settings and controller
gains (param_adapter.py), and the `Vehicle` that composes them for the flight loop (vehicle.py)."""

from fcemu.firmware.vehicle.modes import (
    ACCEPTED,
    ACRO,
    AUTO,
    AUTO_LAND,
    AUTO_LOITER,
    DENIED,
    FAILED,
    FORCE_ARM_MAGIC,
    HOLD,
    IN_AIR,
    LAND,
    LANDING,
    MANUAL,
    MODE_NAMES,
    OFFBOARD,
    ON_GROUND,
    STABILIZED,
    STICK_MODES,
    TEMPORARILY_REJECTED,
    UNSUPPORTED,
    Mode,
    custom_mode,
    mode_from_custom,
    mode_from_parts,
    mode_name,
)
from fcemu.firmware.vehicle.vehicle import SETPOINT_RATE_MAX, Vehicle

__all__ = [
    "ACCEPTED", "ACRO", "AUTO", "AUTO_LAND", "AUTO_LOITER", "DENIED", "FAILED", "FORCE_ARM_MAGIC", "HOLD",
    "IN_AIR", "LAND", "LANDING", "MANUAL", "MODE_NAMES", "OFFBOARD", "ON_GROUND", "SETPOINT_RATE_MAX",
    "STABILIZED", "STICK_MODES", "TEMPORARILY_REJECTED", "UNSUPPORTED", "Mode", "Vehicle", "custom_mode",
    "mode_from_custom", "mode_from_parts", "mode_name",
]
