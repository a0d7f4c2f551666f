"""`fcemu sweep --perturb N`: each trial's policy on N perturbed airframes, judged against the PID.

The same flights as `fcemu eval --controller P --episodes E --seed 7 --perturb N
--perturb-seed S --task T` for T episodic and inflight (the bar's commands, airframes from the
training ranges on a stream training never draws from), pooled over the airframes; the PID is
flown once, after the trials, and each trial's row says whether it meets the deployable bar's
perturbed lines on both tasks: a policy that holds from rest can still ring in flight, where
the rotors already spin and the same command moves the body faster.
"""

from __future__ import annotations

import sys
from typing import Any

from fcemu.evaluation.bar import error_sum, meets_perturbed
from fcemu.sim_bridge.env_config import DEFAULT_AIRFRAME
from fcemu.training.config import TrainConfig

BAR_COMMAND_SEED = 7  # the deployable bar is flown on the commands of `fcemu eval --seed 7`
TASKS = ("episodic", "inflight")  # from rest and from hover: the bar judges both


def perturb_from_args(args, cfg: TrainConfig) -> dict[str, Any]:
    """--perturb N [--perturb-seed S --perturb-episodes E]: the trials' perturbed flight, checked
    here (the ranges load) so a bad value fails before any trial starts."""
    n = getattr(args, "perturb", 0) or 0
    if n == 0:
        return {}
    seed, episodes = args.perturb_seed, args.perturb_episodes
    if n < 0 or seed < 0 or episodes < 1:
        raise ValueError(f"--perturb {n} --perturb-seed {seed} --perturb-episodes {episodes}: expected "
                         "N >= 1 airframes, a seed >= 0 and at least one command")
    from fcemu.sim_bridge.env_config import own_ranges
    from fcemu.sim_bridge.randomization import ranges_for

    ranges = cfg.randomize or own_ranges(cfg.airframe)
    ranges_for(cfg.airframe, ranges)  # RandomizationError is a ValueError
    return {"airframes": n, "seed": seed, "episodes": episodes, "ranges": ranges, "airframe": cfg.airframe}


def fly_summary(controller: str, perturb: dict[str, Any], progress: bool = False) -> dict[str, Any]:
    """Per task, `fcemu eval --controller C --episodes E --seed 7 --perturb N --perturb-seed S
    --task T`, pooled: the Error summed over the axes, each axis's Success and the motors' smoothness."""
    from tqdm import tqdm

    from fcemu.evaluation.metrics import AXES
    from fcemu.evaluation.perturb import fly_perturbed, perturbed_airframes
    from fcemu.evaluation.runner import EvalConfig
    from fcemu.sim_bridge.randomization import ranges_for

    ranges = ranges_for(perturb.get("airframe", DEFAULT_AIRFRAME), perturb["ranges"])
    airframes = perturbed_airframes(ranges, perturb["airframes"], perturb["seed"])
    summary = {}
    with tqdm(total=len(airframes) * len(TASKS), desc=f"{controller} on perturbed airframes", unit="airframe",
              file=sys.stderr, disable=not (progress and sys.stderr.isatty())) as bar:
        for task in TASKS:
            cfg = EvalConfig(episodes=perturb["episodes"], seed=BAR_COMMAND_SEED, task=task)
            m = fly_perturbed(controller, cfg, airframes, perturb["seed"], on_airframe=lambda _: bar.update(),
                              ranges=str(ranges.path)).metrics
            summary[task] = {"error": error_sum(m),
                             "success_pct": [float(m.stat("success_pct", a).mean) for a in AXES],
                             "smoothness": float(m.stat("smoothness", AXES[0]).mean)}
    return summary


def judge(rows: list[dict[str, Any]], perturb: dict[str, Any]) -> dict[str, Any]:
    """The PID flown once on the trials' perturbed airframes; each trial judged against it by
    the deployable bar's perturbed lines (`fcemu.evaluation.bar`) on both tasks. A row's ratio is
    the worse task's, its Success per axis the lower of the two."""
    pid = fly_summary("pid", perturb, progress=True)
    for row in rows:
        p = row["perturbed"]
        if p is None:
            row["perturbed_error_ratio"] = row["perturbed_success_pct"] = row["meets_perturbed"] = None
            continue
        row["perturbed_error_ratio"] = max(p[t]["error"] / pid[t]["error"] for t in TASKS)
        per_task = [p[t]["success_pct"] for t in TASKS]
        row["perturbed_success_pct"] = [min(axis) for axis in zip(*per_task, strict=True)]
        row["meets_perturbed"] = all(meets_perturbed(p[t]["error"], p[t]["success_pct"], pid[t]["error"])
                                     for t in TASKS)
    return pid
