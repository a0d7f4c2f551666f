"""Betaflight's sticks and throttle for fcemu's rates and collective: no SITL needed."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.sitl.betaflight_rc import RcMap


def test_rc_map_round_trips_rates_through_betaflight_sticks():
    rc = RcMap(rate_dps=400.0)
    rates = np.array([1.0, -2.0, 3.0])
    ch = rc.stick_channels(rates)
    assert ch[1] > 1500  # FRD pitch down = Betaflight stick forward
    assert rc.setpoint(ch) == pytest.approx(rates, abs=np.radians(0.8 / 2) + 1e-12)
    thr = rc.throttle_channel(0.745)
    assert abs(rc.fcemu_throttle(thr) - 0.745) < 2e-3
