"""`fcemu bench train`: training throughput and the wall time until the policy beats the PID.

Trains with the defaults of `fcemu train`, evaluating the deterministic policy every
`--eval-every` steps on a fixed set of commands at hover (the in-training evaluation of
`training.train.PidRaceCallback`), and stops when it beats the best PID preset's Error sum
(`--target beat`) or meets the deployable bar's nominal lines (`--target bar`,
`fcemu.evaluation.bar`), or at the cap. Wall time includes the evaluations and a
`--warm-start` (its environment steps are reported apart, not in the steps to beat);
steps/s does not. The machine's load is reported with it.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from fcemu.training.train import PidRaceCallback, TrainConfig, train


class _CappedRace(PidRaceCallback):
    """The race, stopped at the target or at the wall-time cap; times its own evaluations."""

    def __init__(self, cfg: TrainConfig, every: int, target: str, cap_s: float) -> None:
        super().__init__(cfg, every)
        self.target, self.cap_s = target, cap_s
        self.eval_s = 0.0
        self.reached: dict[str, Any] | None = None

    def _on_step(self) -> bool:
        if time.perf_counter() - self._t0 > self.cap_s:
            return False
        if self.num_timesteps < self._next:
            return True
        self._next += self.every
        t = time.perf_counter()
        verdict = self.evaluate()
        self.eval_s += time.perf_counter() - t
        self.logger.record("eval/error_ratio_vs_pid", verdict["error_ratio"])
        hit = verdict["meets_bar"] if self.target == "bar" else verdict["error_ratio"] < 1.0
        if hit:
            self.reached = verdict
        return not hit


def bench_train(args) -> int:
    from fcemu.firmware.errors import UserError
    from fcemu.training.config import from_args

    with tempfile.TemporaryDirectory(prefix="fcemu-bench-train-") as tmp:
        # --steps sets the learning-rate schedule (decay over the run, as `fcemu train`);
        # the wall-time cap or the target usually ends the race first.
        try:
            cfg = from_args(args, out=args.out or str(Path(tmp) / "run"),
                            progress=not args.json and sys.stderr.isatty())
        except ValueError as exc:
            raise UserError(str(exc)) from None
        if cfg.eval_every <= 0:
            raise UserError("the race needs --eval-every > 0")
        load_before = os.getloadavg()
        race = _CappedRace(cfg, cfg.eval_every, args.target, args.budget_s)
        summary = train(cfg, race=race)
    train_s = summary["train_wall_s"]  # with the warm start
    warm_s = summary.get("warm_start", {}).get("wall_s", 0.0)
    reached = race.reached
    result = {
        "algo": cfg.algo,
        "n_envs": cfg.n_envs,
        "hyperparameters": {k: v for k, v in cfg.hyper.items() if k != "policy_kwargs"},
        "torch_threads": cfg.threads,
        "steps": summary["steps"],
        "wall_s": train_s,
        "steps_per_s": round(summary["steps"] / max(train_s - warm_s - race.eval_s, 1e-9), 1),
        "target": args.target,
        "time_to_beat_pid_s": None if reached is None else round(reached["wall_s"], 1),
        "steps_to_beat_pid": None if reached is None else reached["steps"],
        "warm_start_env_steps": summary.get("warm_start", {}).get("env_steps", 0),
        "warm_start_s": warm_s,
        "cap_s": args.budget_s,
        "pid": race.history[-1]["best_pid"] if race.history else None,
        "pid_error_sum": race.history[-1]["pid_error_sum"] if race.history else None,
        "eval_commands": cfg.eval_commands,
        "evaluations": [{"steps": h["steps"], "wall_s": round(h["wall_s"], 1),
                         "error_ratio": round(h["error_ratio"], 4), "meets_bar": h["meets_bar"]}
                        for h in race.history],
        "cpu_count": os.cpu_count(),
        "loadavg_before": [round(x, 2) for x in load_before],
        "loadavg_after": [round(x, 2) for x in os.getloadavg()],
    }
    if args.json:
        print(json.dumps(result))
    else:
        beat = ("not reached" if reached is None else
                f"{result['time_to_beat_pid_s']:.0f} s ({result['steps_to_beat_pid']} steps)")
        print(f"{cfg.algo}: {result['steps_per_s']:.0f} steps/s over {result['steps']} steps; "
              f"time to {args.target} {result['pid']}: {beat}; load {result['loadavg_after']}")
    return 0
