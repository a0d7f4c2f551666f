#!/usr/bin/env python3
"""Take off, hover, flip, land: fly the fcemu SITL (free rig) with body-rate setpoints only.

The vehicle's firmware runs the rate loop; this script is the outer loop a companion
computer would be: attitude from ATTITUDE, position and altitude from LOCAL_POSITION_NED,
and back SET_ATTITUDE_TARGET with type_mask 128 (ignore attitude: body rates in rad/s,
FRD, and thrust 0..1) in PX4 OFFBOARD mode. It runs on the vehicle's clock (time_boot_ms),
so it flies the same whether the SITL runs in real time or N× faster. After touchdown it
idles the motors and disarms only once the vehicle reports itself landed (EXTENDED_SYS_STATE
landed_state ON_GROUND): PX4 refuses a disarm before that.

    fcemu sitl --controller pid            # in one terminal
    python -m fcemu.sitl.demo_flight             # in another (examples/pymavlink_flip.py in a checkout)

Options: --connect (default udpin:0.0.0.0:14550, where the SITL sends to a GCS),
--altitude, --log FILE.npz (the flight, for plotting), --summary FILE.json.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np
from pymavlink import mavutil

M = mavutil.mavlink
G = 9.81
HOVER = 0.745  # Iris hover throttle; the altitude loop's integrator trims the rest
IGNORE_ATTITUDE = 128
FLIP_RATE = 10.0  # rad/s
TOUCHDOWN_TIMEOUT_S = 10.0  # of vehicle time, for the vehicle to report ON_GROUND


class OuterLoop:
    """Position → tilt → body rates; altitude → thrust. Plain PD loops with an altitude integrator."""

    def __init__(self) -> None:
        self.z_int = 0.0

    def rates(self, att, pos, tilt_limit: float = 0.2) -> tuple[float, float, float]:
        # Horizontal hold over the take-off point (yaw stays ~0, so NED x/y ≈ body forward/right):
        # position → a capped velocity → tilt, so that a large offset (after the flip) is flown
        # back at walking pace rather than with ever more speed to brake.
        def tilt(p: float, v: float) -> float:
            v_sp = max(-1.5, min(1.5, -0.8 * p))
            return max(-tilt_limit, min(tilt_limit, 0.25 * (v_sp - v)))

        roll_sp, pitch_sp = tilt(pos.y, pos.vy), -tilt(pos.x, pos.vx)
        k, lim = 5.0, 6.0
        roll_rate = max(-lim, min(lim, k * (roll_sp - att.roll)))
        pitch_rate = max(-lim, min(lim, k * (pitch_sp - att.pitch)))
        return (roll_rate, pitch_rate, 2.0 * -att.yaw)

    def thrust(self, att, pos, z_sp: float, vz_sp: float, dt: float) -> float:
        ez, ev = pos.z - z_sp, pos.vz - vz_sp  # NED: positive = too low / sinking too fast
        self.z_int = max(-1.5, min(1.5, self.z_int + 0.3 * ez * dt))
        accel_up = 1.5 * ez + 2.0 * ev + self.z_int  # m/s² wanted on top of gravity
        tilt = max(0.5, math.cos(att.roll) * math.cos(att.pitch))
        # Thrust grows with rotor speed squared, and throttle sets rotor speed: hence the root.
        return max(0.05, min(1.0, HOVER * math.sqrt(max(0.0, 1.0 + accel_up / G) / tilt)))


def fly(conn, altitude: float, timeout: float, log: list) -> dict:
    conn.mav.command_long_send(conn.target_system, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                               M.MAVLINK_MSG_ID_ATTITUDE, 10_000, 0, 0, 0, 0, 0)
    conn.mav.command_long_send(conn.target_system, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                               M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10_000, 0, 0, 0, 0, 0)
    conn.mav.command_long_send(conn.target_system, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                               M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 100_000, 0, 0, 0, 0, 0)
    outer = OuterLoop()
    pos = conn.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=10)
    if pos is None:
        raise RuntimeError("no LOCAL_POSITION_NED: run the SITL with --rig free")

    def send(rates, thrust, t_ms):
        conn.mav.set_attitude_target_send(t_ms, conn.target_system, 1, IGNORE_ATTITUDE, [1, 0, 0, 0],
                                          *rates, thrust)

    phase, t_phase, t_prev, att, disarm_sent = "offboard", None, None, None, None
    flip_angle, max_alt, flip_time, events = 0.0, 0.0, None, []
    landed: int | None = None  # EXTENDED_SYS_STATE.landed_state, since touchdown
    was_flying = False  # a HEARTBEAT has said armed in OFFBOARD
    wall_deadline = time.monotonic() + timeout
    while time.monotonic() < wall_deadline:
        msg = conn.recv_match(type=["ATTITUDE", "LOCAL_POSITION_NED", "HEARTBEAT", "STATUSTEXT",
                                    "COMMAND_ACK", "EXTENDED_SYS_STATE"], blocking=True, timeout=1.0)
        if msg is None:
            continue
        kind = msg.get_type()
        if kind == "LOCAL_POSITION_NED":
            pos = msg
            continue
        if kind == "STATUSTEXT":
            events.append(msg.text)
            continue
        if kind == "EXTENDED_SYS_STATE":
            landed = msg.landed_state if phase == "touchdown" else None
            continue
        if kind in ("HEARTBEAT", "COMMAND_ACK"):
            disarmed = (not msg.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED if kind == "HEARTBEAT" else
                        msg.command == M.MAV_CMD_COMPONENT_ARM_DISARM and msg.result == M.MAV_RESULT_ACCEPTED)
            if phase == "touchdown" and disarmed:
                phase = "done"
                break
            if kind == "HEARTBEAT":
                mode = mavutil.interpret_px4_mode(msg.base_mode, msg.custom_mode)
                if mode == "OFFBOARD" and not disarmed:
                    was_flying = True
                elif was_flying and phase != "touchdown":  # a failsafe took over: it is not ours to fly
                    state = "disarmed" if disarmed else "armed"
                    events.append(f"the vehicle left OFFBOARD ({mode}, {state})")
                    break
            continue
        att = msg
        t = att.time_boot_ms / 1000.0
        dt = 0.01 if t_prev is None else max(1e-3, min(0.05, t - t_prev))
        t_prev = t
        if t_phase is None:
            t_phase = t
        elapsed = t - t_phase
        alt = -pos.z
        max_alt = max(max_alt, alt)
        rates, thrust = (0.0, 0.0, 0.0), 0.0
        if phase == "offboard":  # PX4's rule: stream first, then switch, then arm
            if elapsed > 0.2:
                conn.set_mode_px4("OFFBOARD", None, None)
                conn.mav.command_long_send(conn.target_system, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                           1, 0, 0, 0, 0, 0, 0)
                phase, t_phase = "takeoff", t
        elif phase in ("takeoff", "hover"):
            climbing = phase == "takeoff" and elapsed < 2.0
            z_sp = -min(altitude, altitude * elapsed / 2.0) if phase == "takeoff" else -altitude
            rates = outer.rates(att, pos)
            thrust = outer.thrust(att, pos, z_sp, -altitude / 2.0 if climbing else 0.0, dt)
            if phase == "takeoff" and elapsed > 4.0:
                phase, t_phase = "hover", t
            elif phase == "hover" and elapsed > 2.0:
                phase, t_phase = "punch", t
        elif phase == "punch":  # climb hard, level, to have height and upward speed for the flip
            rates, thrust = outer.rates(att, pos, tilt_limit=0.0), 1.0
            if elapsed > 0.5:
                phase, t_phase, flip_angle = "flip", t, 0.0
        elif phase == "flip":  # full roll on rates alone, low thrust while inverted
            flip_angle += att.rollspeed * dt
            rates, thrust = (FLIP_RATE, 0.0, 0.0), 0.45
            # Stop early enough that the last of the rotation happens while the rate comes down.
            if flip_angle > 2 * math.pi - 1.0 or (flip_angle > math.pi and -1.0 < att.roll < 0.0):
                phase, t_phase, flip_time = "recover", t, elapsed
                outer.z_int = 0.0
        elif phase == "recover":
            rates = outer.rates(att, pos, tilt_limit=0.1)
            thrust = outer.thrust(att, pos, -altitude, 0.0, dt)
            if elapsed > 3.0:
                phase, t_phase = "landing", t
        elif phase == "landing":  # touch down level and without drift, or a skid can tip it over
            drifting = math.hypot(pos.vx, pos.vy) > 0.4 and alt < 1.2
            speed = 0.0 if drifting else 0.6 if alt > 1.2 else 0.25
            z_sp = pos.z + 0.1 * speed
            rates = outer.rates(att, pos, tilt_limit=0.2 if alt > 0.5 else 0.05)
            thrust = outer.thrust(att, pos, z_sp, speed, dt)
            if alt < 0.2 and elapsed > 1.0:  # within 10 cm of resting height: a bounce would only climb
                phase, t_phase, disarm_sent, landed = "touchdown", t, None, None
        elif phase == "touchdown":  # latched: motors to idle; disarm once the vehicle says it has landed
            if elapsed > TOUCHDOWN_TIMEOUT_S:
                events.append(f"not landed {TOUCHDOWN_TIMEOUT_S:g} s after touchdown (landed_state {landed})")
                break
            if landed == M.MAV_LANDED_STATE_ON_GROUND and (disarm_sent is None or t - disarm_sent > 1.0):
                conn.mav.command_long_send(conn.target_system, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                           0, 0, 0, 0, 0, 0, 0)
                disarm_sent = t
        send(rates, thrust, att.time_boot_ms)
        log.append((t, pos.x, pos.y, pos.z, att.roll, att.pitch, att.yaw, att.rollspeed, att.pitchspeed,
                    att.yawspeed, *rates, thrust))
    if phase == "done":  # how it came to rest, after the motors stopped
        settle_until = time.monotonic() + 1.0
        while (msg := conn.recv_match(type=["ATTITUDE", "LOCAL_POSITION_NED"], blocking=True,
                                      timeout=0.2)) is not None or time.monotonic() < settle_until:
            if time.monotonic() > settle_until:
                break
            if msg is not None:
                att, pos = (msg, pos) if msg.get_type() == "ATTITUDE" else (att, msg)
    cos_tilt = math.cos(att.roll) * math.cos(att.pitch) if att is not None else -1.0
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, cos_tilt))))
    return {"completed": phase == "done" and tilt < 20.0, "phase": phase, "final_tilt_deg": round(tilt, 1),
            "max_altitude_m": round(max_alt, 2),
            "flip_s": None if flip_time is None else round(flip_time, 3),
            "flip_deg": round(math.degrees(flip_angle), 1), "final_altitude_m": round(-pos.z, 2),
            "flight_s": round(log[-1][0] - log[0][0], 2) if log else 0.0, "vehicle_messages": events}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="udpin:0.0.0.0:14550")
    ap.add_argument("--altitude", type=float, default=3.0)
    ap.add_argument("--timeout", type=float, default=120.0, help="wall-clock seconds")
    ap.add_argument("--log", default=None, help="write the flight to this .npz")
    ap.add_argument("--summary", default=None, help="write the summary to this .json")
    args = ap.parse_args(argv)
    conn = mavutil.mavlink_connection(args.connect, source_system=254, source_component=190)
    if conn.wait_heartbeat(timeout=30) is None:
        print("no vehicle heartbeat", file=sys.stderr)
        return 2
    log: list = []
    summary = fly(conn, args.altitude, args.timeout, log)
    if args.log and log:
        cols = ("t x y z roll pitch yaw p q r p_sp q_sp r_sp thrust").split()
        arr = np.array(log)
        np.savez(args.log, **{c: arr[:, i] for i, c in enumerate(cols)})
    if args.summary:
        with open(args.summary, "w") as f:
            json.dump(summary, f, indent=1)
    print(json.dumps(summary))
    return 0 if summary["completed"] else 1


if __name__ == "__main__":
    sys.exit(main())
