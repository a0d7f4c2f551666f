"""The vehicle: what the flight loop calls each tick (a `Commander`: sensors in; armed, setpoint
and controller out), composed of the estimator, the mode machine, the flight tasks and the land
detector.

Ground-station requests reach it as plain method calls (`request_arm`, `request_mode`,
`offboard_setpoint`, `sticks`, `position_fix`, `set_param`), made between ticks by whatever
carries them (firmware/mavlink/bridge.py); it never does I/O. Every time it uses is the loop
clock's, so the failsafe is timed in simulated time and a stuck ground-station process cannot
stall it. Failsafe: offboard setpoints older than COM_OF_LOSS_T (or sticks older than
COM_RC_LOSS_T in a stick mode, once sticks have been seen) → LAND; the vehicle stays in LAND
when the stream returns, the ground station chooses a mode. HOLD and LAND fly the fallback
controller (the PID), whichever controller flies the other modes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import numpy as np

from fcemu.firmware.controller import RateController, RateSetpoint
from fcemu.firmware.controllers import FALLBACK_CONTROLLER
from fcemu.firmware.estimator import GRAVITY, AttitudeEstimator
from fcemu.firmware.loop import Command
from fcemu.firmware.params import CONTROLLERS, ParamTable
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.vehicle import param_adapter
from fcemu.firmware.vehicle.flight_tasks import (
    IDLE,
    FlightInputs,
    FlightTask,
    HoldTask,
    LandTask,
    OffboardTask,
    PositionFix,
    StickTask,
)
from fcemu.firmware.vehicle.land_detector import LandDetector
from fcemu.firmware.vehicle.modes import (
    ACCEPTED,
    ACRO,
    AUTO_MODES,
    HOLD,
    INFO,
    LAND,
    MANUAL,
    OFFBOARD,
    ON_GROUND,
    STABILIZED,
    STICKS_LOSS,
    UNSUPPORTED,
    WARNING,
    Events,
    Mode,
    ModeMachine,
    Reply,
    mode_name,
)

ARM_THROTTLE_MAX = 0.1
SETPOINT_RATE_MAX = 35.0  # rad/s (2000 deg/s, Betaflight's ceiling): the one limit on a rate setpoint


class Vehicle:
    def __init__(self, params: ParamTable, controllers: Mapping[str, RateController],
                 fallback: str = FALLBACK_CONTROLLER, selected: str | None = None) -> None:
        self.params = params
        self.controllers = controllers
        self.fallback = fallback if fallback in controllers else next(iter(controllers))
        self.events = Events()
        self.modes = ModeMachine(self.events)
        self.estimator = AttitudeEstimator()
        self.landed_state = ON_GROUND
        self.now_us = 0
        self._pids = param_adapter.tunable_pids(controllers)
        if selected is not None:
            params.set("CTRL_SEL", CONTROLLERS.index(selected))
        self.settings = param_adapter.VehicleSettings.from_params(params)
        self.inputs = FlightInputs(self.estimator, self.settings, LandDetector())
        stabilized = StickTask(self.inputs, acro=False)
        self.land = LandTask(self.inputs)
        self.tasks: dict[Mode, FlightTask] = {
            MANUAL: stabilized, STABILIZED: stabilized, ACRO: StickTask(self.inputs, acro=True),
            OFFBOARD: OffboardTask(self.inputs), HOLD: HoldTask(self.inputs), LAND: self.land}
        self._last_est_us: int | None = None
        # MAV_CMD_INJECT_FAILURE's (unit, type, instance) → (accepted, text); set where a twin can take it.
        self.failure_injector: Callable[[int, int, int], tuple[bool, str]] | None = None
        self._setpoint = IDLE
        self._command = Command(False, self._setpoint, self.fallback)
        self._apply_params()

    # ---- state, as the ground station sees it ----
    @property
    def armed(self) -> bool:
        return self.modes.armed

    @property
    def mode(self) -> Mode:
        return self.modes.mode

    @property
    def failsafe(self) -> str:
        return self.modes.failsafe

    @property
    def counters(self) -> dict[str, int]:
        return self.events.counters

    @property
    def outbox(self) -> list[tuple[int, str]]:
        return self.events.outbox

    def mode_name(self) -> str:
        return mode_name(self.modes.mode)

    def controller_name(self) -> str:
        return self.settings.controller

    # ---- parameters ----
    def set_param(self, name: str, value: float) -> str:
        problem = self.params.set(name, value)
        if problem:
            self.events.count("param_rejected")
            return problem
        selected = CONTROLLERS[int(self.params["CTRL_SEL"])]
        if name == "CTRL_SEL" and selected not in self.controllers:
            self.events.say(WARNING, f"controller {selected} is not loaded; flying {self.fallback}")
        self._apply_params()
        return ""

    def _apply_params(self) -> None:
        self.settings = self.inputs.settings = param_adapter.VehicleSettings.from_params(self.params)
        name = self.settings.controller
        self._selected = name if name in self.controllers else self.fallback
        param_adapter.apply_pid_gains(self.params, self._pids)

    # ---- requests from the ground station ----
    def request_arm(self, arm: bool, force: bool = False) -> Reply:
        if not arm:
            reply = self.modes.request_disarm(force, self._landed())
            if not self.modes.armed:
                self.landed_state = ON_GROUND
            return reply
        was_armed = self.modes.armed
        reply = self.modes.request_arm("" if force or was_armed else self.arming_problem())
        if self.modes.armed and not was_armed:
            self._activate(on_ground=True, failsafe=False)
        return reply

    def arming_problem(self) -> str:
        inp = self.inputs
        throttle_low = not self._sticks_live() or inp.sticks[3] <= ARM_THROTTLE_MAX
        loaded = self.controller_name() in self.controllers or self.fallback in self.controllers
        return self.modes.arming_problem(self._sensor_problem(), loaded, throttle_low, self._offboard_live())

    def _sensor_problem(self) -> str:
        f = self.inputs.frame
        if f is None or not f.is_finite():
            return "sensors not alive"
        if abs(math.sqrt(sum(a * a for a in f.accel.tolist())) / GRAVITY - 1.0) > 0.3:
            return "accelerometer implausible"
        return ""

    def request_mode(self, mode: Mode) -> Reply:
        before = self.modes.mode
        reply = self.modes.request_mode(mode, self._offboard_live())
        if self.modes.mode != before:
            self._activate(on_ground=self.landed_state == ON_GROUND, failsafe=False)
        return reply

    def offboard_setpoint(self, rates: tuple[float, float, float], thrust: float) -> bool:
        if not (all(math.isfinite(r) and abs(r) <= SETPOINT_RATE_MAX for r in rates)
                and 0.0 <= thrust <= 1.0):
            self.events.count("setpoint_rejected")
            return False
        self.inputs.offboard = RateSetpoint(np.array(rates, dtype=float), float(thrust))
        self.inputs.offboard_us = self.now_us
        return True

    def sticks(self, roll: float, pitch_up: float, yaw: float, throttle: float) -> bool:
        values = (roll, pitch_up, yaw, throttle)
        if not all(math.isfinite(v) for v in values) or not (0.0 <= throttle <= 1.0) \
                or max(abs(roll), abs(pitch_up), abs(yaw)) > 1.0:
            self.events.count("sticks_rejected")
            return False
        self.inputs.sticks = values
        self.inputs.sticks_us = self.now_us
        return True

    def inject_failure(self, unit: int, failure_type: int, instance: int) -> Reply:
        """MAV_CMD_INJECT_FAILURE (SYS_FAILURE_EN was checked by the MAVLink process); said on every link."""
        if self.failure_injector is None:
            return Reply(UNSUPPORTED, "no simulated hardware to fail")
        accepted, text = self.failure_injector(unit, failure_type, instance)
        self.events.count("failure_injected" if accepted else "failure_unsupported")
        self.events.say(WARNING if accepted else INFO, f"Failure injected: {text}" if accepted
                        else f"Failure injection unsupported: {text}")
        return Reply(ACCEPTED if accepted else UNSUPPORTED, text)

    def sensor_failsafe(self, reason: str) -> None:
        """The health monitor lost a sensor the vehicle cannot fly without (firmware/health.py): LAND."""
        if self.modes.armed and self.modes.mode != LAND:
            self.modes.enter_land(reason)
            self._activate(on_ground=self.landed_state == ON_GROUND, failsafe=True)

    def position_fix(self, position: tuple[float, float, float],
                     velocity: tuple[float, float, float]) -> bool:
        """An external position source (NED m, m/s), as PX4 takes vision or motion capture."""
        if not all(math.isfinite(v) for v in (*position, *velocity)):
            self.events.count("position_rejected")
            return False
        self.inputs.fix = PositionFix(self.now_us, position, velocity)
        return True

    # ---- the tick ----
    def command(self, t_us: int, frame: SensorFrame) -> Command:
        self.now_us = t_us
        inp, modes = self.inputs, self.modes
        inp.frame = frame
        self._estimate(frame)
        if not modes.armed:
            self.estimator.vz = 0.0
            self.landed_state = ON_GROUND
            return self._emit(False, self._setpoint)
        s = self.settings
        offboard_lost = t_us - inp.offboard_us > s.of_loss_us
        sticks_lost = inp.sticks_us is not None and t_us - inp.sticks_us > s.rc_loss_us
        if (offboard_lost or sticks_lost) and self._failsafe(offboard_lost, sticks_lost):
            self._activate(on_ground=self.landed_state == ON_GROUND, failsafe=True)
        task = self.tasks[modes.mode]
        sp = task.update(t_us)
        self.landed_state = task.landed_state
        if task is self.land and self.land.touchdown:
            self.modes.disarm(self.land.touchdown)
            self.landed_state = ON_GROUND
            return self._emit(False, self._setpoint)
        self._setpoint = sp
        return self._emit(True, sp)

    def _estimate(self, frame: SensorFrame) -> None:
        """Integrated over the sensors' own clock: a tick the loop skipped (a deadline miss)
        advances the loop clock but not the IMU."""
        g, a = frame.gyro.tolist(), frame.accel.tolist()
        last = self._last_est_us
        dt = 0.001 if last is None else (frame.t_us - last) * 1e-6
        self._last_est_us = frame.t_us
        est = self.estimator
        if (last is None or dt <= 0.0) and not self.modes.armed:
            est.level_from_accel(*a)
        elif 0.0 < dt < 0.1 and math.isfinite(g[0] + g[1] + g[2] + a[0] + a[1] + a[2]):
            est.update(g[0], g[1], g[2], a[0], a[1], a[2], dt)

    def _emit(self, armed: bool, sp: RateSetpoint) -> Command:
        """The tick's Command, reused while nothing in it changed (most ticks)."""
        cmd = self._command
        name = self.fallback if self.modes.mode in AUTO_MODES else self._selected
        if cmd.armed is not armed or cmd.setpoint is not sp or cmd.controller != name:
            cmd = self._command = Command(armed, sp, name)
        return cmd

    def _failsafe(self, offboard_lost: bool, sticks_lost: bool) -> bool:
        reason = self.modes.check_failsafe(offboard_lost, sticks_lost)
        if reason == STICKS_LOSS:
            self.inputs.sticks_us = None  # sticks must come back before they count again
        return bool(reason)

    def _activate(self, on_ground: bool, failsafe: bool) -> None:
        self.tasks[self.modes.mode].activate(self.now_us, on_ground, failsafe)

    def _offboard_live(self) -> bool:
        """PX4's rule: OFFBOARD (and arming in it) only while setpoints arrive within the timeout."""
        return self.now_us - self.inputs.offboard_us <= self.settings.of_loss_us

    def _sticks_live(self) -> bool:
        su = self.inputs.sticks_us
        return su is not None and self.now_us - su <= self.settings.rc_loss_us

    def _landed(self) -> bool:
        """The land detector's verdict; LAND entered on the ground; or the thrust-and-rest test
        on the current setpoint where no task has decided yet."""
        if self.landed_state == ON_GROUND:
            return True
        detector = self.inputs.detector
        if self.modes.mode == LAND and self.land.from_ground:
            return detector.at_rest(self.inputs.frame)
        return detector.from_thrust(self._setpoint.throttle, self.inputs.frame,
                                    self.settings.hover_throttle) == ON_GROUND
