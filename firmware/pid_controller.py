"""The PID rate controller: `RatePID` + `QuadXMixer` behind the `RateController` protocol.

Presets are data files in `firmware/presets/` (`pid_paper.json`: the paper's gains and
Iris mixer; `pid_iris.json`: a tune for the twin, made by the first, Iris-only version of
`benchmarks/tune_pid.py`; `fcemu tune` carries it over to any airframe and writes `pid_<name>.json`;
`pid_betaflight.json`: Betaflight 4.6.0's defaults, checked against the real firmware by
`fcemu betaflight --crosscheck`).
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.mixer import QuadXMixer
from fcemu.firmware.pid import PIDGains, RatePID
from fcemu.firmware.sensors import SensorFrame

PRESET_DIR = Path(str(resources.files("fcemu.firmware") / "presets"))
PRESETS = tuple(sorted(p.stem for p in PRESET_DIR.glob("pid_*.json")))  # the shipped ones
DEFAULT_PRESET = "pid_iris"
_RATE_CHANGE_TICKS = 8  # consecutive off-period ticks that mean a new loop rate, not jitter


def preset_path(name: str) -> Path:
    """A preset by name ("pid_iris", "iris", "pid_paper", "paper") or a path to a JSON file."""
    path = Path(name)
    if path.suffix == ".json":
        if not path.exists():
            raise FileNotFoundError(f"no preset file {path}")
        return path
    stem = name if name.startswith("pid_") else f"pid_{name}"
    if stem not in PRESETS:
        raise ValueError(f"unknown PID preset {name!r}; shipped presets: {', '.join(PRESETS)}")
    return PRESET_DIR / f"{stem}.json"


def load_preset(name: str) -> dict[str, Any]:
    return json.loads(preset_path(name).read_text())


class PIDRateController:
    """Betaflight-style rate PID and Quad X mixer; one `update` per loop tick.

    The PID runs at a fixed nominal period (`dt`, as Betaflight does: a jittering measured
    period would spike D). If the loop's `dt` stays more than 20% off that period for a few
    ticks in a row, the loop runs at another rate and the filters are recomputed for it.
    """

    def __init__(self, gains: PIDGains, mixer: QuadXMixer | None = None, dt: float = 0.001,
                 name: str = "pid") -> None:
        self.name = name
        self.pid = RatePID(gains, dt)
        self.mixer = mixer or QuadXMixer()
        self._off_period = 0

    @classmethod
    def from_preset(cls, name: str = DEFAULT_PRESET, dt: float = 0.001) -> PIDRateController:
        return cls.from_dict(load_preset(name), dt)

    @classmethod
    def from_dict(cls, preset: dict[str, Any], dt: float = 0.001) -> PIDRateController:
        gains = PIDGains.from_dict(preset["pid"])
        mixer = QuadXMixer(**preset.get("mixer", {}))
        return cls(gains, mixer, dt, name=preset.get("name", "pid"))

    def to_dict(self) -> dict[str, Any]:
        m = self.mixer
        return {"name": self.name, "pid": self.pid.gains.to_dict(),
                "mixer": {"table": m.table_name if m.table_name != "custom" else [list(r) for r in m.table],
                          "idle": m.idle, "airmode": m.airmode,
                          **({"yaw_reversed": True} if m.yaw_reversed else {})}}

    @property
    def dt(self) -> float:
        return self.pid.dt

    @property
    def gains(self) -> PIDGains:
        return self.pid.gains

    def set_gains(self, gains: PIDGains) -> None:
        """New gains in flight (from parameters); integrator and filter states are kept."""
        if gains != self.pid.gains:
            self.pid.set_gains(gains)

    def reset(self) -> None:
        self.pid.reset()
        self.mixer.reset()

    def take_over(self, setpoint: RateSetpoint, frame: SensorFrame) -> None:
        """Start mid-flight from another controller: no D or feedforward kick (`RatePID.take_over`)."""
        self.pid.take_over(np.asarray(setpoint.rates, dtype=float).tolist(), frame.gyro.tolist())
        self.mixer.reset()

    def update(self, setpoint: RateSetpoint, frame: SensorFrame, dt: float) -> np.ndarray:
        nominal = self.pid.dt
        if abs(dt - nominal) > 0.2 * nominal:
            self._off_period += 1
            if self._off_period >= _RATE_CHANGE_TICKS:
                self.pid.set_dt(dt)
                self._off_period = 0
        else:
            self._off_period = 0
        rates = setpoint.rates
        demand = self.pid.update(
            rates.tolist() if isinstance(rates, np.ndarray) else rates,
            frame.gyro.tolist(),
            self.mixer.mix_range,
        )
        return np.array(self.mixer.mix(demand, setpoint.throttle))
