"""The health rules (firmware/health.py): what is detected, in how many ticks, and what the loop does."""

from __future__ import annotations

import math

import numpy as np

from fcemu.firmware.controllers import DEFAULT_POLICY, load_controller
from fcemu.firmware.health import HealthMonitor, HealthRules
from fcemu.firmware.loop import FlightLoop, ScriptedCommander
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.timing import LockstepClock
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sim_bridge.faults import Fault, FaultInjector
from fcemu.sim_bridge.link import InProcessLink
from fcemu.sim_bridge.twin import Twin, TwinState

ACCEL = np.array([0.0, 0.0, -9.81])
IRIS = airframe_spec("iris")
IRIS_RULES = HealthRules.for_airframe(IRIS)


def _frame(k: int, gyro, speed, gyro_t: int | None = None, speed_t=None) -> SensorFrame:
    return SensorFrame(k * 1000, np.asarray(gyro, float), ACCEL, np.asarray(speed, float), gyro_t,
                       None if speed_t is None else np.asarray(speed_t, dtype=np.int64))


def _hover(k: int) -> tuple[list[float], list[float], np.ndarray]:
    """A vehicle wobbling at hover: rates and speeds that change every tick, a command that follows."""
    pwm = np.array([1700.0, 1700.0, 1700.0, 1700.0]) + 40.0 * math.sin(k / 7.0) * np.array([1, -1, -1, 1])
    return [0.3 * math.sin(k / 7.0), 0.1, 0.0], list((pwm - 1000.0) * 1.1), pwm


def _run(monitor: HealthMonitor, ticks: int, corrupt=None) -> list[SensorFrame]:
    out = []
    for k in range(ticks):
        gyro, speed, pwm = _hover(k)
        if corrupt is not None:
            gyro, speed, pwm = corrupt(k, gyro, speed, pwm)
        out.append(monitor.check(_frame(k, gyro, speed), pwm))
    return out


def test_a_healthy_vehicle_is_left_alone() -> None:
    m = HealthMonitor(IRIS_RULES)
    frames = [_frame(k, *_hover(k)[:2]) for k in range(500)]
    seen = [m.check(f, _hover(k)[2]) for k, f in enumerate(frames)]
    assert all(a is b for a, b in zip(seen, frames, strict=True))
    assert m.policy_trusted and not m.failsafe and not m.detected and not m.outbox


def test_gyro_glitches_are_held_over_and_a_dead_gyro_fails_to_land() -> None:
    m = HealthMonitor(IRIS_RULES)
    spikes = _run(m, 300, lambda k, g, s, p: ([40.0, 0, 0] if k % 50 == 10 else g, s, p))
    assert m.glitches == 6 and not m.gyro_failed and m.policy_trusted
    assert spikes[60].gyro.tolist() == _hover(59)[0]  # the spike read as the last good sample
    m = HealthMonitor(IRIS_RULES)
    frames = _run(m, 200, lambda k, g, s, p: ([math.nan] * 3 if k >= 100 else g, s, p))
    assert m.gyro_failed and m.failsafe == "gyro implausible" and not m.policy_trusted
    assert m.detected["gyro_failed"] - 1 - 100 == 19  # the 20th absent sample
    assert frames[-1].gyro.tolist() == [0.0, 0.0, 0.0]
    assert [text for _, text in m.outbox] == ["Gyro implausible: rate feedback lost",
                                              "Policy hands over to PID: gyro implausible"]


def test_a_stuck_gyro_is_detected_only_while_a_torque_is_asked_for() -> None:
    m = HealthMonitor(IRIS_RULES)
    _run(m, 300, lambda k, g, s, p: ([0.2, 0.1, 0.0] if k >= 100 else g, s, p))
    # 50 ticks with a torque asked for (the wobble passes through level now and then)
    assert m.failsafe == "gyro stuck" and 49 <= m.detected["gyro_failed"] - 1 - 100 < 80
    m = HealthMonitor(IRIS_RULES)  # level hover, motors even: a still gyro is what a still vehicle reads
    _run(m, 300, lambda k, g, s, p: ([0.0, 0.0, 0.0], [770.0] * 4, np.full(4, 1700.0)))
    assert not m.detected


def test_a_lost_rotor_speed_frame_is_held_and_flown_on() -> None:
    def absent(k, g, s, p):
        return g, [math.nan, *s[1:]] if k == 100 else s, p

    m = HealthMonitor(IRIS_RULES)
    frames = _run(m, 200, absent)
    assert m.policy_trusted and not m.detected and not m.outbox
    assert frames[100].rotor_speed.tolist() == [_hover(99)[1][0], *_hover(100)[1][1:]]
    assert frames[101].rotor_speed.tolist() == _hover(101)[1]
    rng = np.random.default_rng(0)  # 5 % of every motor's frames lost, each as NaN or as its last sample
    m = HealthMonitor(IRIS_RULES)
    _run(m, 2000, lambda k, g, s, p: (g, [math.nan if rng.random() < 0.05 else v for v in s], p))
    assert m.policy_trusted and not m.detected


def test_old_telemetry_hands_over_at_its_age_limit() -> None:
    """Frames that stop coming (the last sample and its time held) hand over once older than 20 ms
    (NN_ESC_MAX_AGE); a held sample younger than that is flown on."""
    m = HealthMonitor(IRIS_RULES)
    for k in range(300):
        gyro, speed, pwm = _hover(k)
        sample = min(k, 100)  # motor 3's telemetry stops after tick 100
        speed[2] = _hover(sample)[1][2]
        m.check(_frame(k, gyro, speed, k * 1000, [k * 1000, k * 1000, sample * 1000, k * 1000]), pwm)
        if k == 120:
            assert m.policy_trusted
    assert m.handover == "rotor speed 3 too old" and m.detected["handover"] - 1 == 121


def test_a_lossy_link_hands_over_on_its_loss_rate() -> None:
    """Every other frame of motor 1 lost: never 20 ms old, but half its frames lost over 100 ms
    (NN_ESC_LOSS_MAX 0.2 over NN_ESC_LOSS_WIN 0.1 s)."""
    m = HealthMonitor(IRIS_RULES)
    _run(m, 300, lambda k, g, s, p: (g, [math.nan if k >= 100 and k % 2 else s[0], *s[1:]], p))
    assert m.handover == "rotor speed 1 losing frames"
    assert 30 < m.detected["handover"] - 1 - 100 < 80
    for spec in ("esc_loss_max", "esc_max_age_s", "gyro_max_age_s", "esc_max_lag_s"):
        assert spec in HealthRules.__dataclass_fields__


def test_an_old_gyro_sample_fails_the_gyro() -> None:
    """A gyro sample older than 10 ms (NN_GYRO_MAX_AGE, PX4's mc_nn_control) fails the gyro as a dead
    one does; a repeated sample with its old time is a lost frame, never a stuck gyro."""
    m = HealthMonitor(IRIS_RULES)
    for k in range(200):
        _, speed, pwm = _hover(k)
        sampled = k if k < 100 else 100 + (k - 100) // 8 * 8  # a sample every 8 ms: 7 ms old at most
        m.check(_frame(k, _hover(sampled)[0], speed, sampled * 1000), pwm)
    assert not m.detected
    m = HealthMonitor(IRIS_RULES)
    for k in range(200):
        _, speed, pwm = _hover(k)
        sampled = min(k, 100)
        m.check(_frame(k, _hover(sampled)[0], speed, sampled * 1000), pwm)
    assert m.failsafe == "gyro stale" and m.detected["gyro_failed"] - 1 == 111
    assert m.handover == "gyro stale" and not m.policy_trusted


def _telemetry_of(pwm: list[np.ndarray], delay: int, gain: float = 1.0) -> list[list[float]]:
    """What an ESC reports of rotors that follow `pwm` as the Iris's motors do, `delay` ticks late;
    `gain` scales their speed command (a sagging battery)."""
    rules = IRIS_RULES
    up = 1.0 - math.exp(-1e-3 / rules.motor_tau_up_s)
    down = 1.0 - math.exp(-1e-3 / rules.motor_tau_down_s)
    per_us = rules.rotor_speed_max / (rules.pwm_max - rules.pwm_min)
    speed = [(pwm[0][i] - rules.pwm_min) * per_us for i in range(4)]
    out = []
    for p in pwm:
        command = [(v - rules.pwm_min) * per_us * gain for v in p]
        speed = [w + (up if c > w else down) * (c - w) for w, c in zip(speed, command, strict=True)]
        out.append(speed)
    return [out[0]] * delay + out[: len(out) - delay]


def test_late_telemetry_is_found_by_its_lag_and_brought_forward_by_the_model() -> None:
    """The delay that best fits the telemetry to the model of the commanded speed: 5 ms is found within
    100 ms of moving commands and the policy flies on readings brought forward by the model over the
    fitted lag; 2 ms (an ESC's own pipeline) is not found, nor is a still rotor."""
    pwm = [np.array([1600.0, 1600.0, 1600.0, 1600.0]) + 80.0 * math.sin(k / 15.0) * np.array([1, -1, -1, 1])
           for k in range(400)]
    on_time = np.array(_telemetry_of(pwm, 0))

    read: list[np.ndarray] = []

    def fly(delay: int, commands: list[np.ndarray], gain: float = 1.0) -> HealthMonitor:
        m = HealthMonitor(IRIS_RULES)
        read.clear()
        for k, (p, w) in enumerate(zip(commands, _telemetry_of(commands, delay, gain), strict=True)):
            read.append(m.check(_frame(k, _hover(k)[0], w), p).rotor_speed)  # the reading after `p`
        return m

    for delay in (5, 10):
        late = fly(delay, pwm)
        assert late.policy_trusted and not late.handover and late.detected["esc_late"] < 100
        after = late.detected["esc_late"] + 1
        raw = np.abs(np.array(_telemetry_of(pwm, delay))[after:] - on_time[after:]).mean()
        brought_forward = np.abs(np.array(read)[after:] - on_time[after:]).mean()
        assert raw > 10.0 and brought_forward < 0.02 * raw, (delay, raw, brought_forward)
    assert not fly(2, pwm).detected
    assert not fly(0, pwm).detected
    still = [np.full(4, 1600.0)] * 400
    assert not fly(5, still).detected
    assert not fly(0, pwm, gain=0.75).detected  # a rotor short of its command is not late

    def stale(k, g, s, p):
        return g, [*s[:2], 700.0 if k >= 100 else s[2], s[3]], p

    m = HealthMonitor(IRIS_RULES)
    _run(m, 300, stale)
    assert m.handover == "rotor speed 3 stale" and 100 < m.detected["handover"] < 160

    def dead(k, g, s, p):
        return g, [*s[:3], s[3] * math.exp(-(k - 100) / 25.0) if k >= 100 else s[3]], p

    m = HealthMonitor(IRIS_RULES)
    _run(m, 300, dead)
    assert m.handover == "rotor speed 4 implausible"
    m.reset()
    assert m.policy_trusted and not m.detected

    m = HealthMonitor(IRIS_RULES)
    m.policy_flying = False  # the PID flies: it does not read rotor speed, nothing to hand over
    _run(m, 300, stale)
    assert m.policy_trusted and not m.handover and not m.outbox


def _fly_policy(fault: Fault | None, ticks: int = 400, at: int = 200) -> tuple[list[str], FlightLoop]:
    """The default policy on the twin through rate steps at 0.1 and 0.25 s, `fault` injected at tick `at`."""
    twin = Twin(rig="rig")
    first = twin.reset(0, TwinState(rotor_speed=(780.0,) * 4))
    controllers = {"main": load_controller(str(DEFAULT_POLICY), airframe=IRIS),
                   "pid": load_controller("pid", airframe=IRIS)}
    schedule = [(0.0, (0.0, 0.0, 0.0), 0.7), (0.1, (2.0, 0.0, 0.0), 0.7), (0.25, (-2.0, 1.0, 0.0), 0.7)]
    commander = ScriptedCommander(schedule, controller="main")
    loop = FlightLoop(InProcessLink(twin), first, controllers, commander, LockstepClock(), fallback="pid",
                      health=HealthMonitor(IRIS_RULES))
    flown = []
    for k in range(ticks):
        if k == at and fault is not None:
            twin.faults = FaultInjector(twin.dt, IRIS.max_rotor_speed, 3)
            twin.faults.inject(fault)
        flown.append(loop.tick(k * 1000).controller)
    return flown, loop


def test_the_loop_flies_the_pid_once_the_policy_cannot_be_trusted() -> None:
    flown, loop = _fly_policy(Fault("esc-telemetry", "intermittent", 2, 0.5))
    assert set(flown[:200]) == {"main"} and flown[-1] == "pid" and not loop.faults
    assert loop.health.handover == "rotor speed 2 losing frames"



def test_the_policy_flies_on_late_telemetry_brought_forward() -> None:
    flown, loop = _fly_policy(Fault("esc-telemetry", "delayed", 0, 0.005), at=150)
    assert set(flown) == {"main"} and loop.health.policy_trusted
    assert loop.health.detected["esc_late"] - 150 <= 100


def test_the_policy_flies_on_through_ordinary_telemetry_loss() -> None:
    for fault in (Fault("esc-telemetry", "intermittent", 0, 0.05), Fault("esc-telemetry", "burst", 0, 0.01)):
        flown, loop = _fly_policy(fault, at=50)
        assert set(flown) == {"main"} and not loop.health.detected, fault


def test_a_vehicle_armed_at_steady_hover_is_not_stale() -> None:
    """Armed with the rotors already at hover (the in-flight task): the first frame was read under the
    disarmed PWM, yet the steady reading matches the hover PWM that follows; once that PWM moves and
    the reading does not, it is stale."""
    m = HealthMonitor(IRIS_RULES)
    hover_pwm, speed = np.full(4, 1700.0), [770.0] * 4
    m.check(_frame(0, [0, 0, 0], speed), np.full(4, 1000.0))  # the PWM written while disarmed
    for k in range(1, 200):
        m.check(_frame(k, [0, 0, 0], speed), hover_pwm)
    assert m.policy_trusted and not m.detected
    moved = np.array([1700.0, 1700.0, 1700.0, 1710.0])
    for k in range(200, 221):
        m.check(_frame(k, [0, 0, 0], speed), moved)
    assert m.handover == "rotor speed 4 stale" and m.detected["handover"] == 220


def test_a_late_tick_does_not_fail_a_good_gyro() -> None:
    """A tick 80 ms late at a pitch step's onset (a loaded host): the vehicle turned further than one
    tick allows, and the gyro is judged over the time the twin stepped through, not one tick."""
    twin = Twin(rig="rig")
    first = twin.reset(0, TwinState(rotor_speed=(780.0,) * 4))
    schedule = [(0.0, (0.0, 0.0, 0.0), 0.5), (0.1, (0.0, math.radians(60.0), 0.0), 0.5)]
    loop = FlightLoop(InProcessLink(twin), first, {"pid": load_controller("pid", airframe=IRIS)},
                      ScriptedCommander(schedule, controller="pid"), LockstepClock(),
                      health=HealthMonitor(IRIS_RULES))
    t_us = 0
    while t_us < 400_000:
        loop.tick(t_us)
        t_us += 1000
        if t_us == 101_000:
            loop._hold_outputs(80)
            t_us += 80_000
    assert not loop.health.detected and loop.health.glitches == 0
    assert abs(loop.frame.gyro[1] - math.radians(60.0)) < 0.1


def test_a_garbage_gyro_earns_no_room_while_its_samples_are_held() -> None:
    """Uniform garbage over the full scale: each sample judged over one tick from the last good one,
    so it fails in about 20 ticks; room grown over the held run would take garbage for a turn."""
    top = math.radians(2000.0)
    for seed in range(20):
        rng = np.random.default_rng(seed)
        m = HealthMonitor(IRIS_RULES)
        _run(m, 200, lambda k, g, s, p, rng=rng: (list(rng.uniform(-top, top, 3)) if k >= 100 else g, s, p))
        assert m.failsafe == "gyro implausible" and m.detected["gyro_failed"] - 1 - 100 <= 22
