"""Faults named on a command line, and the faults a twin server's session starts with."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.cli import build_parser
from fcemu.sim_bridge.fault_spec import parse_fault, session_faults
from fcemu.sim_bridge.faults import Fault
from fcemu.sim_bridge.twin import Twin

pytestmark = pytest.mark.timeout(30)


def test_twin_serve_takes_faults_in_the_eval_grammar() -> None:
    args = build_parser().parse_args(["twin", "serve", "--fault", "esc-telemetry:1:off",
                                      "--fault", "gyro:burst:20ms@1%"])
    assert args.fault == [Fault("esc-telemetry", "off", 1), Fault("gyro", "burst", 0, 0.01, 0.02)]
    assert build_parser().parse_args(["twin", "serve"]).fault is None


def test_twin_serve_refuses_a_bad_fault_on_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args(["twin", "serve", "--fault", "esc-telemetry:sometimes"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "argument --fault" in err and "esc-telemetry has no fault 'sometimes'" in err


def test_session_faults_are_seeded_by_the_reset_and_start_over() -> None:
    twin = Twin(rig="rig")
    faults = [parse_fault("esc-telemetry:intermittent:50%")]
    draws = [session_faults(twin, faults, seed).rng.random(8).tolist() for seed in (7, 7, 8)]
    assert draws[0] == draws[1] != draws[2]
    assert draws[0] != np.random.default_rng(7).random(8).tolist()  # not the twin's noise stream
    injector = session_faults(twin, faults, 7)
    assert injector is not None and injector.faults == faults
    assert session_faults(twin, [], 7) is None
    with pytest.raises(ValueError):
        session_faults(twin, faults, -1)
