"""How long `fcemu fit`'s stages are expected to take, for the estimate of the time left its log
lines carry (`evaluation.progress.Stages`).

The tune takes its budget, its bound included; given a PID, an uncached bound takes its programmes.
The other stages take what their work takes on this machine: their seconds at the defaults on 2 cores
(docs/results/fit.md), scaled by the work asked for, then by the pace the finished stages showed. An
estimate, said to be one.
"""

from __future__ import annotations

from typing import Any

from fcemu.evaluation.progress import Stages
from fcemu.training.fit_options import STUDENT_STEPS, FitOptions

# Seconds at the defaults: the teacher's flights on 20 tuning commands, one student's DAgger (6 rounds
# of 1000 steps on 64 twins, 3000 Adam steps a round) and its motors' flight, the check's four flights
# of 50 held-out commands.
TYPICAL_S = {"teacher": 110.0, "policy": 90.0, "check": 20.0}
BOUND_S_PER_COMMAND = 2.0  # an uncached bound's programmes (crude boxes), per held-out command, 2 cores
MCU_S = 10.0  # `fcemu bench mcu`: build and run


def _bound_s(opts: FitOptions) -> float:
    """An uncached bound's seconds; none where it is cached or the airframe has none."""
    from fcemu.evaluation.bound import HORIZON, rig_constants
    from fcemu.firmware.errors import UserError
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.sim_bridge.tasks import episodic_commands
    from fcemu.training.pid_tune import bound_cache_path

    try:
        rig = rig_constants(load_airframe(opts.airframe))
    except UserError:
        return 0.0
    if bound_cache_path(rig, episodic_commands(opts.seed + 1, opts.episodes), HORIZON).exists():
        return 0.0
    return BOUND_S_PER_COMMAND * opts.episodes


def expected_s(opts: FitOptions) -> dict[str, float]:
    """Each stage's expected seconds, before any has run."""
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.training.fit_teacher import SPEED_COMMANDS, student_kind

    steps = opts.steps or STUDENT_STEPS[student_kind(load_airframe(opts.airframe))]
    student = opts.rounds / 6 * (0.5 * steps * opts.envs / (STUDENT_STEPS["exact"] * 64)
                                 + 0.5 * opts.fit_steps / 3000)
    out = {"tune": opts.tune_budget_s if opts.pid is None else _bound_s(opts),
           "teacher": TYPICAL_S["teacher"] * min(SPEED_COMMANDS, opts.episodes) / SPEED_COMMANDS,
           "policy": TYPICAL_S["policy"] * student,
           "check": TYPICAL_S["check"] * opts.episodes / 50 + (MCU_S if opts.mcu else 0.0)}
    if opts.lag_multiple is not None:
        del out["teacher"]
    return out


def fit_stages(opts: FitOptions, log: Any) -> Stages:
    """The fit's stages; the tune's seconds are its budget's on any machine, so only the rest set the pace."""
    return Stages(expected_s(opts), log, calibrate=("teacher", "policy", "check"))
