"""`fcemu tune`'s options, each declared once (`training.options`): its parser, its defaults, the
command in its preset and summary. Apart from `training.pid_tune`, which loads MuJoCo: every
`fcemu` command line builds this parser."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from fcemu.firmware.timing import available_cpus
from fcemu.training.options import JSON_HELP, REQUIRED, add_arguments, option

GYRO_NOISE = 0.01  # rad/s white noise per sample, a MEMS gyro's order at 1 kHz


@dataclass(frozen=True, kw_only=True)
class TuneOptions:
    """What a tune does; its summary's "command" repeats it."""

    airframe: str = option(REQUIRED, "sim_bridge/airframes/<name>.json or a path to an airframe file",
                           metavar="NAME|FILE")
    seed: int = option(2018, "seed of the tuning commands; the held-out commands are seed + 1")
    episodes: int = option(50, "tuning commands")
    check_episodes: int = option(50, "held-out commands")
    rounds: int = option(12, "most rounds of the search per stage, if the budget lasts")
    budget_s: float = option(570.0, "seconds of the whole tune: the bound on the held-out commands (its "
                                    "solve time counted even where it is cached), the search and the "
                                    "held-out check", metavar="S")
    jobs: int = option(0, "worker processes flying candidates (0: one per CPU this process may use)",
                       metavar="J")
    gyro_noise: float = option(GYRO_NOISE, "the noisy gyro stage's white noise, rad/s per sample", cli=False)

    def __post_init__(self) -> None:
        if not self.jobs:
            object.__setattr__(self, "jobs", available_cpus())


@dataclass(frozen=True, kw_only=True)
class TuneCommand:
    """What `fcemu tune` takes besides the tune's options."""

    out: str = option(REQUIRED, "where pid.json, tune.json, tune_report.md and tune_step_response.png are "
                                       "written", metavar="DIR")
    json: bool = option(False, JSON_HELP)


def register_tune(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tune", help="tune the Betaflight-style rate PID for an airframe: the Iris tune "
                                    "carried over by physics, then searched; checked against `fcemu bound`")
    add_arguments(p, TuneOptions, TuneCommand)
    p.set_defaults(handler="fcemu.training.pid_tune_cli:tune_command")
