"""A peer flying the vehicle in OFFBOARD while a test does something else: the valid setpoint
stream, the vehicle's once-a-second counters, its HEARTBEAT and its parameter list."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M

from fcemu.firmware.params import ParamTable

ROOT = Path(__file__).resolve().parents[3]

SETPOINT_EVERY_S = 0.02
HOVER = ParamTable()["MPC_THR_HOVER"]


class Flight:
    """The offboard peer's valid setpoint stream, kept going between whatever else the test does."""

    def __init__(self, off, gcs) -> None:
        self.off, self.gcs = off, gcs
        self.rates = (0.0, 0.0, 0.0)
        self.thrust = HOVER
        self._next = 0.0
        self.received: dict[str, int] = {}

    def tick(self) -> None:
        now = time.monotonic()
        if now >= self._next:
            self.off.mav.set_attitude_target_send(0, 1, 1, 128, [1, 0, 0, 0], *self.rates, self.thrust)
            self._next = now + SETPOINT_EVERY_S

    def fly(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.tick()
            for conn in (self.off, self.gcs):
                while (m := conn.recv_msg()) is not None:
                    self.received[m.get_type()] = self.received.get(m.get_type(), 0) + 1
            time.sleep(0.005)

    def counters(self) -> dict[str, int]:
        """The vehicle's next once-a-second report (NAMED_VALUE_INT), flying meanwhile."""
        wanted = {"rx_frames", "rx_bad", "rx_rejecte", "rx_foreign", "loop_miss", "loop_ticks"}
        for _ in range(100_000):  # only reports sent from now on
            if self.gcs.recv_msg() is None:
                break
        got: dict[str, int] = {}
        deadline = time.monotonic() + 10
        while wanted - set(got) and time.monotonic() < deadline:
            self.tick()
            m = self.gcs.recv_match(type="NAMED_VALUE_INT", blocking=True, timeout=0.01)
            if m is not None:
                got[m.name] = m.value
        assert not wanted - set(got), f"no counters from the vehicle: {got}"
        return got

    def heartbeat(self):
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            self.tick()
            m = self.gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=0.01)
            if m is not None and m.get_srcSystem() == 1:
                return m
        raise AssertionError("no HEARTBEAT")


def params(conn, flight: Flight) -> dict[str, float]:
    for _ in range(100_000):  # what queued meanwhile first: a full socket buffer would drop the list
        if conn.recv_msg() is None:
            break
    conn.mav.param_request_list_send(1, 1)
    values: dict[str, float] = {}
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        flight.tick()
        pv = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.01)
        if pv is not None:
            values[pv.param_id] = pv.param_value
            if len(values) == pv.param_count:
                return values
    raise AssertionError(f"parameter list incomplete: {len(values)}")


def assert_offboard_and_armed(flight: Flight) -> None:
    hb = flight.heartbeat()
    assert mavutil.interpret_px4_mode(hb.base_mode, hb.custom_mode) == "OFFBOARD"
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED


def flood_against_baseline(flight: Flight, kind: str, address: tuple[str, int], frames_per_s: float,
                           seconds: float) -> dict:
    """Baseline (flying, no flood), flood (a flooder process sending `kind` to `address`), baseline
    again: the loop's misses per tick in the baseline windows pooled and under the flood (the
    shared machine's load drifts, so the baseline brackets the flood), and the counters."""
    windows = {"base": [0, 0], "flood": [0, 0]}
    first = before = flight.counters()
    sent = 0
    for name in ("base", "flood", "base"):
        flooder = None
        if name == "flood":
            flooder = subprocess.Popen([sys.executable, "-m", "tests.firmware.mavlink.flooder", kind,
                                        address[0], str(address[1]), str(frames_per_s), str(seconds)],
                                       cwd=ROOT, stdout=subprocess.PIPE, text=True)
        flight.fly(seconds if name == "flood" else seconds / 2)
        if flooder is not None:
            sent = int(flooder.communicate(timeout=60)[0])
            assert_offboard_and_armed(flight)
        after = flight.counters()
        windows[name][0] += after["loop_miss"] - before["loop_miss"]
        windows[name][1] += after["loop_ticks"] - before["loop_ticks"]
        before = after
    (base_misses, base_ticks), (flood_misses, flood_ticks) = windows["base"], windows["flood"]
    result = {"sent": sent, "base_rate": base_misses / max(base_ticks, 1), "base_ticks": base_ticks,
              "flood_rate": flood_misses / max(flood_ticks, 1), "flood_ticks": flood_ticks,
              "first": first, "last": before}
    print(f"{kind} flood: {result}")
    return result
