"""`fcemu fit`'s options, each declared once (`training.options`): the fit's parser, its defaults, the
command in its report and its JSON. A module of their own, so that the stages (`fit_teacher`,
`fit_report`) import what they read without importing the fit that composes them."""

from __future__ import annotations

from dataclasses import dataclass

from fcemu.firmware.timing import available_cpus
from fcemu.training.options import JSON_HELP, REQUIRED, option

# Steps per twin and DAgger round: one 1 s episode; a student of sensed history has noise to average
# and needs twice the transients (docs/results/fit.md).
STUDENT_STEPS = {"exact": 1000, "sensed": 2000}


@dataclass(frozen=True, kw_only=True)
class FitOptions:
    """What a fit does; `fit_report.command_line` repeats it."""

    airframe: str = option(REQUIRED, "a shipped airframe's name or an airframe file")
    out: str = option(REQUIRED, "directory for pid.json, policy.onnx, report.md, fit.json")
    seed: int = option(2018, "seed of the tuning commands, on which the PID is tuned and the teacher chosen, "
                             "and of the policy's fit; the held-out check flies seed + 1")
    episodes: int = option(50, "commands tuned on (seed), and held out (seed + 1)")
    # The fit's 15 minutes on two cores: a 7-inch quad's teacher and policy took 340 s of them.
    tune_budget_s: float = option(480.0, "seconds of the PID tune: its bound, search and check (`fcemu tune "
                                         "--budget-s`)")
    rounds: int = option(6, "DAgger rounds of the policy's fit")
    steps: int | None = option(None, f"steps per twin and DAgger round (default: {STUDENT_STEPS['exact']}, "
                                     f"{STUDENT_STEPS['sensed']} where the sensors are not the truth)")
    envs: int = option(64, "twins flown together in the policy's fit")
    fit_steps: int = option(3000, "Adam steps after each DAgger round")
    # The largest two layers of 10 inputs well inside an F405's budget.
    net_arch: tuple[int, ...] = option((48, 48), "the policy's hidden layers, tanh", nargs="+", metavar="H",
                                       parse=tuple)
    lag_multiple: float | None = option(None, "the teacher's time constant in motor lags (default: chosen "
                                              "on the tuning commands)")
    damping: float | None = option(None, "the teacher's damping ratio (default: 0.7, about 4 %% of "
                                         "overshoot, or 0.85 where that lowers the Peaks on the tuning "
                                         "commands)")
    yaw_first: float | None = option(None, "the share of yaw's need the teacher serves before roll and "
                                           "pitch's while they gather speed (default: chosen on the tuning "
                                           "commands, 0 or 0.3)", metavar="SHARE")
    braking: float | None = option(None, "the teacher's braking curve's jerk, in shares of each axis's "
                                         "authority per motor lag (default: chosen on the tuning commands, "
                                         "0.5, 0.3 or 0.2)", metavar="SHARE")
    pid: str | None = option(None, "a PID already tuned for this airframe (a preset name or file): no tune "
                                   "(default: the one `fcemu tune` wrote to OUT/pid.json for it, else a "
                                   "shipped airframe's own)", metavar="PRESET")
    jobs: int = option(0, "worker processes and torch threads (0: one per CPU this process may use)",
                       recorded=False)
    mcu: bool = option(True, "skip the policy's time on an STM32F405, which `fcemu bench mcu` measures",
                       recorded=False)
    progress: bool = option(True, "the policy fit's progress bar", cli=False)

    def __post_init__(self) -> None:
        if not self.jobs:
            object.__setattr__(self, "jobs", available_cpus())


@dataclass(frozen=True, kw_only=True)
class FitCommand:
    """What `fcemu fit` takes besides the fit's options."""

    tune: bool = option(False, "tune a PID anew even where the airframe's ships")
    json: bool = option(False, JSON_HELP)


def shipped_pid(airframe: str) -> str | None:
    """The shipped tune of a shipped airframe named by name (`firmware/presets/pid_<name>.json`), or
    None. An airframe file is tuned anew, whatever name it gives itself."""
    from fcemu.firmware.controllers import ControllerSpecError, airframe_preset
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    if airframe.endswith(".json") or "/" in airframe:
        return None
    try:
        return str(airframe_preset(airframe_spec(airframe)))
    except ControllerSpecError:
        return None
