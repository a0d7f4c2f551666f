"""The Betaflight patch's lag rule and read-ahead (flight/neural_lag.c), compiled on the host, against
fcemu's HealthMonitor on the same telemetry: the same late bus found at the same tick, read ahead to
the same speeds."""

from __future__ import annotations

import math
import re
import shutil
import subprocess

import numpy as np
import pytest

from fcemu.export.betaflight.build import PATCH, check_contract, health_header
from fcemu.firmware.health import HealthMonitor, HealthRules
from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.airframe_spec import airframe_spec
from tests.export.mcu_tools import SHIPPED
from tests.firmware.test_health import _telemetry_of as telemetry_of

RULES = HealthRules.for_airframe(airframe_spec("iris"))

# One motor per line in, read-ahead speed (or the reading, until the bus is found late) out; a bus is
# late once any motor's fit says so, as NEURAL's lagTick keeps it (rpmAhead).
DRIVER = r"""
#include <stdio.h>
#include "flight/neural_lag.h"
int main(void) {
    neuralLag_t lag[4];
    float pwm[4], speed[4];
    int tick = 0, ahead = 0;
    while (scanf("%f %f %f %f %f %f %f %f", &pwm[0], &pwm[1], &pwm[2], &pwm[3],
                 &speed[0], &speed[1], &speed[2], &speed[3]) == 8) {
        for (int i = 0; i < 4; i++) {
            if (tick == 0) neuralLagStart(&lag[i], speed[i]);
            if (neuralLagTick(&lag[i], pwm[i], 1, tick > 0, speed[i], LIMIT_TICKS) && !ahead) {
                ahead = 1;
                printf("late %d\n", tick);
            }
        }
        for (int i = 0; i < 4; i++) printf("%.4f ", ahead ? neuralLagAhead(&lag[i], speed[i]) : speed[i]);
        printf("\n");
        tick++;
    }
    return 0;
}
"""


def _new_file(name: str) -> str:
    """A file the patch adds, as it adds it."""
    part = re.split(r"(?m)^(?=diff -ruN )", PATCH.read_text())
    section = next(p for p in part if p.startswith(f"diff -ruN a/{name} "))
    return "".join(line[1:] for line in section.splitlines(keepends=True)[4:])


@pytest.fixture(scope="module")
def lag_rule(tmp_path_factory):
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("no gcc on PATH")
    root = tmp_path_factory.mktemp("neural_lag")
    (root / "flight" / "neural").mkdir(parents=True)
    (root / "flight" / "neural_lag.h").write_text(_new_file("src/main/flight/neural_lag.h"))
    (root / "flight" / "neural_lag.c").write_text(_new_file("src/main/flight/neural_lag.c"))
    (root / "flight" / "neural" / "fcemu_health.h").write_text(health_header(check_contract(SHIPPED)))
    (root / "flight" / "neural" / "fcemu_policy.h").write_text("#define FCEMU_LOOP_RATE_HZ 1000.0f\n")
    (root / "driver.c").write_text(DRIVER)
    limit = RULES.esc_max_lag_s * 1000.0
    subprocess.run([gcc, "-std=c11", "-O1", f"-DLIMIT_TICKS={limit}f", "-I", str(root), "-o",
                    str(root / "lag"), str(root / "driver.c"), str(root / "flight" / "neural_lag.c"), "-lm"],
                   check=True)
    return root / "lag"


def _flight(delay: int, ticks: int = 400) -> tuple[list[np.ndarray], list[list[float]]]:
    """Commands that move, and the Iris's rotors following them, reported `delay` ticks late."""
    swing = np.array([1.0, -1.0, -1.0, 1.0])
    pwm = [np.full(4, 1600.0) + 80.0 * math.sin(k / 15.0) * swing for k in range(ticks)]
    return pwm, telemetry_of(pwm, delay)


@pytest.mark.parametrize("delay", [0, 2, 5, 10])
def test_the_patch_finds_a_late_bus_and_reads_it_ahead_as_the_firmware_does(lag_rule, delay):
    pwm, telemetry = _flight(delay)
    feed = "".join(" ".join(f"{v:.6f}" for v in (*p, *w)) + "\n" for p, w in zip(pwm, telemetry, strict=True))
    out = subprocess.run([str(lag_rule)], input=feed, capture_output=True, text=True, check=True).stdout
    late = [int(line.split()[1]) for line in out.splitlines() if line.startswith("late")]
    c_read = np.array([[float(v) for v in line.split()] for line in out.splitlines()
                       if not line.startswith("late")])

    monitor = HealthMonitor(RULES)
    read = []
    for k, (p, w) in enumerate(zip(pwm, telemetry, strict=True)):
        gyro = np.array([0.3 * math.sin(k / 7.0), 0.1, 0.0])  # a live gyro: a still one would be "stuck"
        frame = SensorFrame(k * 1000, gyro, np.array([0.0, 0.0, -9.81]), np.asarray(w))
        read.append(monitor.check(frame, p).rotor_speed)
    found = monitor.detected.get("esc_late")
    if delay <= 2:
        assert found is None and late == []
        return
    assert found is not None and late and abs(late[0] - (found - 1)) <= 1, (late, found)
    after = max(late[0], found) + 1
    gap = np.abs(c_read[after:] - np.array(read)[after:]).max()
    print(f"delay {delay}: found at {late[0]} (fcemu {found - 1}), read-ahead within {gap:.4f} rad/s")
    assert gap < 0.01  # rad/s, float32 against float64
    assert np.abs(c_read[after:] - np.array(telemetry)[after:]).mean() > 10.0  # and read ahead it was
