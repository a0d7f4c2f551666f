"""A PARAM_REQUEST_LIST flood (20,000 requests a second for 10 s from another local process) costs
the vehicle one table update per request: the list streams within the link's budget, the
flight's peer keeps the vehicle in OFFBOARD and armed, the loop keeps its deadlines."""

from __future__ import annotations

import time

import pytest
from pymavlink.dialects.v20 import common as M

from tests.firmware.mavlink.conftest import command, connect
from tests.firmware.mavlink.flight import Flight, assert_offboard_and_armed, flood_against_baseline, params

pytestmark = pytest.mark.timeout(180)


def test_a_param_list_flood_does_not_bring_the_vehicle_down(sitl) -> None:
    s = sitl(rig="rig", duration=300.0)
    gcs, off = connect(s.gcs_port), connect(s.offboard_port, source_system=245, source_component=190)
    flight = Flight(off, gcs)
    flight.fly(0.3)
    off.set_mode_px4("OFFBOARD", None, None)
    flight.fly(0.3)
    assert command(off, M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == M.MAV_RESULT_ACCEPTED
    flight.fly(1.0)
    assert_offboard_and_armed(flight)
    listed = params(gcs, flight)
    values_before = flight.received.get("PARAM_VALUE", 0)
    r = flood_against_baseline(flight, "param_list", next(iter(gcs.clients)), 20_000, 10.0)
    values = flight.received.get("PARAM_VALUE", 0) - values_before
    assert r["sent"] > 100_000
    assert r["base_ticks"] > 5000 and r["flood_ticks"] > 5000
    assert r["flood_rate"] <= 2 * r["base_rate"] + 0.01
    assert_offboard_and_armed(flight)
    # The flood's lists went out within the link's budget (1,000 PARAM_VALUE a second), not 32 a request.
    assert values <= 1500 * 20.0, values
    # A real ground station's request afterwards gets the whole list, promptly.
    start = time.monotonic()
    assert params(gcs, flight) == listed
    assert time.monotonic() - start < 5.0
    out = s.stop()
    assert "Traceback" not in out, out[-3000:]
