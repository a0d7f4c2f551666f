"""Real Betaflight flies the twin: configure the SITL over its CLI, arm it, fly rate steps, record.

Sticks and throttle: `sitl.betaflight_rc.RcMap`.

NEURAL. A firmware from `fcemu export --target betaflight` (`firmware=`) gets the NEURAL box on
AUX2 and its gyro filters off (`neural_settings`), so that `gyro.gyroADCf`, the policy's input,
is the twin's gyro as fcemu's policy sees it. In the SITL the policy steps once per FDM packet,
the first time on the first packet after NEURAL is seen on. With `neural=True` each episode
sends the sticks and AUX2 high in an RC packet alone and waits until Betaflight reports them
read (MSP_RC; its RX task runs on its own schedule) before the first tick, so the policy starts
fresh on that tick, as fcemu's does. Its debug mode is NEURAL: `neural_health()` reads what the
mode's sensor-health rules made of the episode (the state, why and when the policy was dropped,
the oldest rpm telemetry and the largest loss rate it flew on).

Clock. The SITL's clock is not the twin's: it integrates wall time times the ratio of the last
pair of FDM timestamp steps to their arrival interval. Each episode reads that clock over MSP
(the RTC, which counts its millis()) before and after its ticks; `clock_drift` is the SITL's
elapsed time over the twin's, minus 1.

Episodes. Betaflight's PID state lives in the firmware, so each episode starts by disarming and
re-arming it (which clears the I-term), then puts the twin at rest and raises the throttle and
the sticks on the same step, as `fcemu eval` starts its episodes.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from fcemu.sim_bridge.betaflight_link import BetaflightBridge
from fcemu.sitl.betaflight_blackbox import BLACKBOX_SETTINGS, await_logs, write_blackbox
from fcemu.sitl.betaflight_process import (
    NEURAL_STATES,
    BetaflightError,
    BetaflightMsp,
    BetaflightSitl,
    NeuralFirmware,
)
from fcemu.sitl.betaflight_rc import RcMap
from fcemu.sitl.traces import Traces

ARM_CH_US = 1900
DISARM_CH_US = 1000
STALL_STEPS = 10  # consecutive unanswered FDM packets that mean the SITL has stopped
MAX_LOST_PER_EPISODE = 3  # more lost answers than this and the episode is flown again

# The CLI configuration `fcemu betaflight` applies on top of Betaflight 4.6's defaults. The first
# block is what flying on the rig needs; the second switches off what acts on the RC link or on
# throttle changes rather than in the rate loop (see README, "Real Betaflight on the twin").
BASE_SETTINGS = (
    "aux 0 0 0 1700 2100 0 0",  # ARM on AUX1 high
    "set small_angle = 180",  # the rig may be at any attitude when an episode re-arms
    "set pwr_on_arm_grace = 0",
    "set runaway_takeoff_prevention = OFF",  # a take-off check: it disarms on saturated steps
    "set motor_pwm_protocol = PWM",
    "set rates_type = ACTUAL",
)
CROSSCHECK_SETTINGS = (
    "set rc_smoothing = OFF",
    "set f_roll = 0", "set f_pitch = 0", "set f_yaw = 0",
    "set d_max_roll = 0", "set d_max_pitch = 0",
    "set throttle_boost = 0",
    "set anti_gravity_gain = 0",
)
NEURAL_CH = 5  # AUX2
NEURAL_ON_US = 1900
RC_MATCH_US = 2  # MSP_RC reports the channels as read, to the µs
RC_POLL_S = 0.005
FIRST_REPLY_TIMEOUT_S = 1.0


def neural_settings(firmware: NeuralFirmware) -> list[str]:
    """The SITL keeps its 8 kHz PID loop: its NEURAL mode ticks once per FDM packet (see
    export/betaflight/neural.patch, flight/neural.c)."""
    return [f"aux 1 {firmware.box_id} 1 1700 2100 0 0",  # NEURAL on AUX2 high
            # the SITL has no dynamic notch (USE_DYN_NOTCH_FILTER is off in its target)
            "set gyro_lpf1_static_hz = 0", "set gyro_lpf1_dyn_min_hz = 0", "set gyro_lpf2_static_hz = 0",
            "set debug_mode = NEURAL"]  # the sensor-health verdicts over MSP_DEBUG (neural_health)


class _Stalled(Exception):
    """The SITL stopped answering FDM packets."""


class BetaflightFlight:
    """One SITL process and one bridge: configure, wait until armable, arm, fly, disarm."""

    def __init__(self, run_dir: str | Path, twin, rc: RcMap | None = None,
                 settings: Sequence[str] = CROSSCHECK_SETTINGS, speed: float = 1.0,
                 ready_timeout_s: float = 20.0, retries: int = 3,
                 firmware: NeuralFirmware | None = None, neural: bool = False,
                 blackbox: str | Path | None = None) -> None:
        if neural and firmware is None:
            raise BetaflightError("NEURAL needs a firmware exported with `fcemu export --target betaflight`")
        self.firmware = firmware
        self.neural = neural
        self.clock_drift: list[float] = []  # per accepted episode
        self._last_drift = 0.0
        self.speed = speed
        self.retries = retries
        self.restarts = 0
        self.episode_packets: dict[str, int] = {}  # the last accepted episode's, as PacketStats.to_json
        self.run_dir = Path(run_dir)
        self.twin = twin
        self.rc = rc or RcMap()
        self.settings = [*BASE_SETTINGS, *self.rc.settings(), *settings,
                         *(neural_settings(firmware) if firmware else []),
                         *(BLACKBOX_SETTINGS if blackbox is not None else ())]
        self.blackbox = None if blackbox is None else Path(blackbox)  # written on close (betaflight_blackbox)
        self.blackbox_logs = 0
        self.ready_timeout_s = ready_timeout_s
        self.sitl = BetaflightSitl(self.run_dir, firmware.binary if firmware else None)
        self.bridge: BetaflightBridge | None = None
        self.centre = [1500, 1500, 1000, 1500, DISARM_CH_US, 1000]

    def __enter__(self) -> BetaflightFlight:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        self.sitl.fresh_eeprom()
        self.sitl.configure(self.settings)
        self.bridge = BetaflightBridge(self.twin, speed=self.speed,
                                       send_rotor_speed=self.firmware is not None)
        self.wait_ready()

    def close(self) -> None:
        if self.bridge is not None:
            bridge = self.bridge
            if self.blackbox is not None:  # Betaflight closes a log a few loops after the disarm
                await_logs(self.run_dir, lambda: bridge.step(self.centre))
            bridge.close()
            self.bridge = None
        self.sitl.stop()
        if self.blackbox is not None:
            self.blackbox_logs = write_blackbox(self.run_dir, self.blackbox)[1]

    def _flags(self) -> list[str]:
        return self._msp(lambda msp: msp.arming_disable_flags())

    @staticmethod
    def _msp(call):
        msp = BetaflightMsp()
        try:
            return call(msp)
        finally:
            msp.close()

    def wait_ready(self) -> None:
        """Stream the twin at rest, switch low, until Betaflight has no reason not to arm
        (gyro calibration, RX). A SITL whose scheduler never starts (it can happen at boot on a
        loaded host: no answers, or BOOTGRACE, which is 0 s here, never clears) is restarted."""
        assert self.bridge is not None
        for attempt in range(self.retries + 1):
            if attempt:
                self.sitl.stop()
                self.sitl.start()
                self.restarts += 1
            if self._ready():
                return
        raise BetaflightError(f"Betaflight SITL did not start flying after {self.retries + 1} starts; "
                              f"see {self.sitl.log_path}")

    def _ready(self) -> bool:
        assert self.bridge is not None
        waited, flags = 0.0, ["?"]
        while waited < self.ready_timeout_s:
            for _ in range(round(0.25 / self.bridge.dt)):
                self.bridge.reset_twin()
                self.bridge.step(self.centre)
                if self.bridge.silent_steps >= STALL_STEPS and waited >= 1.0:
                    return False
            waited += 0.25
            try:
                flags = self._flags()
            except BetaflightError:  # its TCP listener was lost at boot (see BetaflightSitl.cli)
                return False
            if not flags:
                self._msp(lambda msp: msp.set_clock())
                return True
            if "BOOTGRACE" in flags and waited >= 2.0:
                return False
        raise BetaflightError(f"Betaflight refuses to arm: arming disabled by {' '.join(flags)} "
                              f"after {self.ready_timeout_s:g} s")

    def arm(self, timeout_s: float = 1.0, attempts: int = 3) -> None:
        """Arm switch high until the motors spin. On a loaded host an attempt can fail with no
        flag left to show for it once the switch is low again, and the next one succeed: each
        failed attempt is followed by 0.3 s with the switch low. The error names the flags read
        while the switch was still high."""
        assert self.bridge is not None
        rc = [1500, 1500, 1000, 1500, ARM_CH_US, 1000]
        for _ in range(attempts):
            for _ in range(round(timeout_s / self.bridge.dt)):
                self.bridge.step(rc)
                if min(self.bridge.outputs) > 0.5 * self.rc.motor_idle:
                    return
                if self.bridge.silent_steps >= STALL_STEPS:
                    raise _Stalled
            flags = self._flags()  # read with the switch still high: the reason it was refused
            self.bridge.idle(self.centre, 0.3)
        reason = " ".join(flags) if flags else "no flag set (it never saw the switch?)"
        raise BetaflightError(f"Betaflight refuses to arm: arming disabled by {reason}")

    def disarm(self, timeout_s: float = 1.0) -> None:
        assert self.bridge is not None
        for _ in range(round(timeout_s / self.bridge.dt)):
            self.bridge.reset_twin()
            self.bridge.step(self.centre)
            if max(self.bridge.outputs) == 0.0:
                return
            if self.bridge.silent_steps >= STALL_STEPS:
                raise _Stalled
        raise BetaflightError("Betaflight did not disarm when the arm switch went low")

    def restart(self) -> None:
        """A new SITL process on the saved eeprom (after it stopped answering)."""
        self.sitl.stop()
        self.sitl.start()
        self.restarts += 1
        self.wait_ready()

    def _await_rc(self, rc: Sequence[int], timeout_s: float = 2.0) -> None:
        """Until Betaflight has read `rc` (MSP_RC), which its RX task does on its own schedule."""
        end = time.monotonic() + timeout_s
        while True:
            seen = self._msp(lambda msp: msp.rc_channels())[:len(rc)]
            seen[2:4] = seen[3:1:-1]  # MSP_RC is in Betaflight's order (roll, pitch, yaw, throttle)
            if len(seen) == len(rc) and max(abs(a - b) for a, b in zip(seen, rc, strict=True)) <= RC_MATCH_US:
                return
            if time.monotonic() > end:
                raise BetaflightError(f"Betaflight did not read the RC channels {list(rc)} within "
                                      f"{timeout_s:g} s (it reads {seen})")
            time.sleep(RC_POLL_S)

    def sitl_clock_ms(self) -> int:
        return self._msp(lambda msp: msp.clock_ms())

    def neural_health(self) -> dict[str, object]:
        """What the NEURAL mode's sensor-health rules made of the flight since it was last switched on
        (its DEBUG_NEURAL values; ticks are the policy's, 1 ms): the state now, why the policy was
        dropped ("" if it was not) and after how many ticks, the oldest rpm telemetry (ticks since a
        motor's last valid frame) and the largest loss rate it flew on, the ticks it flew, and the
        largest rpm delay its lag rule judged, µs (0: none judged)."""
        v = self._msp(lambda msp: msp.debug_values())
        return {"state": NEURAL_STATES[v[0]], "dropped": NEURAL_STATES[v[1]] if v[1] else "",
                "dropped_after_ticks": v[2] if v[1] else None, "max_rpm_age_ticks": v[3],
                "max_loss_rate": v[4] / 1000.0, "gyro_age_ticks": v[5], "policy_ticks": v[6],
                "max_lag_us": v[7]}

    def fly_episode(self, rates_frd: Sequence[float], throttle_ch: int, ticks: int,
                    rate: np.ndarray, pwm: np.ndarray, on_tick: Callable[[int], None] | None = None) -> int:
        """Re-arm, put the twin at rest, hold the step for `ticks` steps; fills rate (gyro sent to
        Betaflight) and pwm (what it answered) per step. Returns how many steps were late.

        An episode in which Betaflight lost an answer or disarmed is flown again on a restarted
        SITL (its clock can break under host load; see README), at most `retries` times.
        `on_tick(k)` runs before step k (e.g. to inject a fault into the twin)."""
        assert self.bridge is not None
        why = ""
        for attempt in range(self.retries + 1):
            if attempt:
                self.restart()
            stats = self.bridge.stats
            before = stats.to_json()
            try:
                self._fly(rates_frd, throttle_ch, ticks, rate, pwm, on_tick)
            except _Stalled:
                why = "it stopped answering"
                continue
            self.episode_packets = {k: v - before[k] for k, v in stats.to_json().items()}
            lost = self.episode_packets["lost"]
            # disarmed = every motor at mincommand (a policy may put one motor there, armed)
            if lost <= MAX_LOST_PER_EPISODE and pwm.max(axis=1).min() > 1000.0:
                self.clock_drift.append(self._last_drift)
                return self.episode_packets["late"]
            why = f"{lost} answers lost" if lost > MAX_LOST_PER_EPISODE else "it disarmed mid-episode"
        raise BetaflightError(f"Betaflight SITL failed an episode {self.retries + 1} times (last: {why}); "
                              f"see {self.sitl.log_path}")

    def _fly(self, rates_frd: Sequence[float], throttle_ch: int, ticks: int,
             rate: np.ndarray, pwm: np.ndarray, on_tick: Callable[[int], None] | None = None) -> None:
        assert self.bridge is not None
        self.disarm()
        self.bridge.idle(self.centre, 0.02)  # the arm switch must be seen low before it counts
        self.arm()
        roll, pitch, yaw = self.rc.stick_channels(rates_frd)
        rc = [roll, pitch, throttle_ch, yaw, ARM_CH_US, NEURAL_ON_US if self.neural else 1000]
        self.bridge.reset_twin()
        if self.neural:  # NEURAL on before the first tick: the policy's first step is that tick's
            self.bridge.send_rc(rc)
            self._await_rc(rc)
        clock0 = self.sitl_clock_ms()
        self.bridge.drain()
        for k in range(ticks):  # the first answer after the pauses above may take long (see step)
            if on_tick is not None:
                on_tick(k)
            frame, out, _ = self.bridge.step(rc, FIRST_REPLY_TIMEOUT_S if k == 0 else None)
            rate[k] = frame.gyro
            pwm[k] = out
            if self.bridge.silent_steps >= STALL_STEPS:
                raise _Stalled
        self._last_drift = (self.sitl_clock_ms() - clock0) / (ticks * self.bridge.dt * 1000.0) - 1.0

    def fly_script(self, commander, duration_s: float,
                   neural_window_s: tuple[float, float] | None = None) -> Traces:
        """Fly a `firmware.loop` commander's setpoints and throttle as sticks (e.g. the free rig's
        take-off and doublets of `fcemu sitl --no-mavlink`); one continuous-task trace. With
        `neural_window_s` = (on, off) the NEURAL switch is high between those times."""
        assert self.bridge is not None
        self.disarm()
        self.bridge.idle(self.centre, 0.02)
        self.arm()
        ticks = round(duration_s / self.bridge.dt)
        setpoint, rate, pwm = np.zeros((1, ticks, 3)), np.zeros((1, ticks, 3)), np.zeros((1, ticks, 4))
        neural = np.zeros(ticks, dtype=bool)
        altitude = np.zeros(ticks)
        frame = self.bridge.frame
        top = 0.0
        for k in range(ticks):
            command = commander.command(k * self.bridge.twin.dt_us, frame)
            sticks = self.rc.stick_channels(command.setpoint.rates)
            t = k * self.bridge.dt
            on = neural_window_s is not None and neural_window_s[0] <= t < neural_window_s[1]
            rc = [sticks[0], sticks[1], self.rc.throttle_channel(command.setpoint.throttle), sticks[2],
                  ARM_CH_US, NEURAL_ON_US if on else 1000]
            neural[k] = on
            frame, out, _ = self.bridge.step(rc)
            setpoint[0, k] = self.rc.setpoint(sticks)
            rate[0, k] = frame.gyro
            pwm[0, k] = out
            altitude[k] = -float(self.twin.truth().position[2])
            top = max(top, altitude[k])
        with contextlib.suppress(_Stalled):
            self.disarm()
        stats = self.bridge.stats
        return Traces(np.arange(ticks) * self.bridge.dt, setpoint, rate, pwm,
                      controller="betaflight-4.6.0-sitl" + ("-neural" if self.firmware else ""),
                      task="continuous",
                      extra={"rig": self.twin.rig, "max_altitude_m": top, "neural_on": neural.tolist(),
                             "altitude_m": altitude.tolist(), "final_altitude_m": float(altitude[-1]),
                             "packets": {**stats.to_json(), "sitl_restarts": self.restarts}})

    def fly_steps(self, commands: np.ndarray, throttle_ch: int, episode_s: float = 1.0,
                  on_episode: Callable[[int], None] | None = None) -> Traces:
        """Fly each (already quantised) FRD command as one episode; traces in fcemu's format."""
        assert self.bridge is not None
        n, ticks = len(commands), round(episode_s / self.bridge.dt)
        rate, pwm = np.zeros((n, ticks, 3)), np.zeros((n, ticks, 4))
        late = []
        for i, cmd in enumerate(commands):
            late.append(self.fly_episode(cmd, throttle_ch, ticks, rate[i], pwm[i]))
            if on_episode is not None:
                on_episode(i)
        with contextlib.suppress(_Stalled):
            self.disarm()
        setpoint = np.broadcast_to(np.asarray(commands)[:, None, :], (n, ticks, 3)).copy()
        t = np.arange(ticks) * self.bridge.dt
        stats = self.bridge.stats
        name = "betaflight-4.6.0-sitl" + ("-neural" if self.neural else "")
        return Traces(t, setpoint, rate, pwm, controller=name, task="episodic",
                      extra={"throttle_channel": throttle_ch, "rate_dps": self.rc.rate_dps,
                             "late_per_episode": late, "clock_drift_per_episode": list(self.clock_drift),
                             "packets": {**stats.to_json(), "sitl_restarts": self.restarts},
                             "reply_us_p50": _pct(stats.reply_us, 50),
                             "reply_us_p99": _pct(stats.reply_us, 99),
                             "settings": self.settings})


def _pct(values: list[int], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None
