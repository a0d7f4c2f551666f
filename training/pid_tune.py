"""A Betaflight-style rate PID tuned for any airframe in minutes (`fcemu tune`: `training.pid_tune_cli`).

    fcemu tune --airframe x500 --out runs/tune_x500 --json

The start is the Iris tune (`firmware/presets/pid_iris.json`) carried over by physics, so the
search has little left to do. Per axis, B is the angular acceleration per unit PID output
(demand → mixer → PWM → rotor speed → thrust at hover → torque → rate, linearised at hover
from the MuJoCo rig), and τ the motor lag plus any ESC and gyro delay. A P gain sets the
crossover kp·B, which a lag τ limits to ∝ 1/τ; so from the reference airframe r:

    kp = kp_r·(B_r/B)·(τ_r/τ)      ki = ki_r·(B_r/B)·(τ_r/τ)²
    kd = kd_r·(B_r/B)              kff = kff_r·(B_r/B)      filter cut-offs ×τ_r/τ

(D and feedforward add an acceleration per rate change: dimensionless, so only B scales
them.) An axis of less authority than the reference's gets its pidsum limit raised (up to the
whole output range) to keep the reference's angular acceleration at the limit. The search
bounds move with the gains, ten times wider either way: the carry-over is good to a factor of
several, not better. Then `pid_search.pattern_search` refines the start in two stages, each
axis's gains moved together first (its loop gain) and then each knob alone,
on the tuning commands (seed S): on the noise-free twin, then with a gyro of 0.01 rad/s white
noise, where the cost caps the motors' roughness (mean |Δpwm|) at `SMOOTHNESS_CAP` × the noise
allowance: the start's roughness on the same noisy gyro, or the reference tune's on its own airframe
where that is larger, so no gain buys step response with motor noise. The result
is checked on held-out commands (seed S + 1) against `fcemu bound`'s lower bound on the Error
(`evaluation.bound`), and written as a preset that `--controller pid:DIR/pid.json` flies.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from fcemu.evaluation.pid_carry_over import (
    FILTER_KNOBS,
    REFERENCE,
    LoopPhysics,
    gain_scale,
    iris_tune_carried_over,
    loop_physics,
    mixer_for,
    nominal,
    per_axis,
)
from fcemu.firmware.errors import UserError
from fcemu.firmware.mixer import QuadXMixer
from fcemu.firmware.pid_controller import load_preset
from fcemu.sim_bridge.airframe import Airframe, load_airframe
from fcemu.sim_bridge.tasks import episodic_commands
from fcemu.training.pid_search import (
    AXES,
    AxisGains,
    CandidatePool,
    Knob,
    Move,
    Score,
    SearchState,
    pattern_search,
)
from fcemu.training.tune_options import TuneOptions

COST_VERSION = "fcemu-pid-tune/4"
SMOOTHNESS_CAP = 1.2  # motor |Δpwm| on the noisy gyro, at most this × the noise allowance
# The allowance is the start's roughness on the noisy gyro, but never below the reference tune's on its
# own airframe: a motor command is |Δpwm| in µs whatever the airframe, and the reference tune flies real
# Betaflight at that level, so a start the physics made quiet is not walled in far below every other
# tune (docs/results/pid_tune.md).
SETTLE_MARGIN_PCT = 6.0
TIMES_BOUND_LINE = 1.3
SUCCESS_LINE = 99.8
# The held-out bound's McCormick envelope is over the crude rate boxes (`evaluation.bound.Floor`): as
# sound, at most a few % lower, in half the time of the tight boxes' five programmes.
TIGHT_BOUND = False
LEAST_SEARCH_SHARE = 0.5  # of the budget the search and check keep, however long the bound took
# Searched knobs: (setting, axes, step, (lowest, highest) for the reference airframe). Gains
# bounds scale with the gains (module doc); cut-offs with τ, within what a 1 kHz loop can run.
GAIN_KNOBS = (("kp", (0, 1, 2), 1.3, (0.5, 40.0)), ("ki", (0, 1, 2), 1.5, (1.0, 100.0)),
              ("kd", (0, 1, 2), 1.4, (0.001, 0.1)), ("kff", (0, 1, 2), 1.4, (0.05, 5.0)))
# The carried-over gains are right to within a factor of several, not better (the Crazyflie's best
# tune flies 3 to 7 times its start): the gains' bounds are this much wider either way, and each
# axis's gains also move together (`AxisGains`), by AXIS_GAIN_STEP at first.
GAIN_SLACK = 10.0
AXIS_GAIN_STEP = 2.0
PIDSUM_KNOB = (1.25, (0.2, 1.0))


def settle_limits(airframe: Airframe, commands: np.ndarray) -> dict[str, Any]:
    """What physics allows Success: per axis, the largest angular acceleration any motor command
    gives (each motor at full thrust where it helps, off where it does not; no lag, no spin-up),
    the largest command that could still meet Success's rule (mean |Ω* − Ω| over 0.5–1 s at most
    10 % of it) flying at that acceleration from rest, and how many of `commands` ask for more:
    no controller settles those, so they fail Success on that axis."""
    from fcemu.evaluation.bound import authority, rig_constants
    from fcemu.evaluation.metrics import SETTLE_S, SUCCESS_BAND

    rig = rig_constants(nominal(airframe))
    accel = authority(rig.B, rig.kf, rig.w_max)
    window = np.linspace(SETTLE_S, 1.0, 501)

    def settles(e0: float, a: float) -> bool:
        return float(np.maximum(e0 - a * window, 0.0).mean()) <= SUCCESS_BAND * e0

    largest = []
    for a in accel:
        lo, hi = 0.0, a * 2.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if settles(mid, a) else (lo, mid)
        largest.append(lo)
    over = (np.abs(np.asarray(commands)) > np.array(largest)).sum(axis=0)
    return {"max_angular_acceleration_rad_s2": per_axis(accel), "largest_settleable_rad_s": per_axis(largest),
            "unsettleable_commands": {a: int(n) for a, n in zip(AXES, over, strict=True)}}


def knobs_for(ref: LoopPhysics, new: LoopPhysics, reference: dict[str, Any]) -> list[Move]:
    """The search's moves: each axis's gains together first, then every knob alone. A D term the
    reference leaves off (Betaflight's yaw) starts, if the search turns it on, at the D to P ratio
    of the reference's roll: D's time constant; a D worth the roll's acceleration per rate change
    would be too much for the axis's start P to carry."""
    _, speed, scale = gain_scale(ref, new)
    pid = reference["pid"]
    d_time = pid["kd"][0] / pid["kp"][0]
    first_d = d_time * np.array(pid["kp"]) * scale["kp"]
    gains = [Knob(f"{key}_{AXES[i]}", key, i, step, lo * scale[key][i] / GAIN_SLACK,
                  hi * scale[key][i] * GAIN_SLACK, first=float(first_d[i]) if key == "kd" else 0.0)
             for key, axes, step, (lo, hi) in GAIN_KNOBS for i in axes]
    knobs: list[Move] = [AxisGains(f"gains_{a}", tuple(k for k in gains if k.axis == i), AXIS_GAIN_STEP)
                         for i, a in enumerate(AXES)]
    knobs += gains
    for key, step, (lo, hi) in FILTER_KNOBS:
        knobs.append(Knob(key, key, None, step, min(lo * speed, hi), hi))
    step, (lo, hi) = PIDSUM_KNOB
    knobs += [Knob(f"pidsum_{a}", "pidsum_limit", i, step, lo, hi) for i, a in enumerate(AXES)]
    return knobs


def cost(s: Score, ref: Score, noisy: bool, floor_us: float = 0.0) -> float:
    """The search's cost (COST_VERSION), relative to the start `ref` on the same twin and commands.

    3·ΣError/ΣError_ref + 0.5·Σ Rise/Rise_ref + 0.05 per % of Peak above max(110 %, the start's)
    + (100 − Success %)/5 per axis + 0.1 per % of the worst episode's settling error above
    SETTLE_MARGIN_PCT of |e0| (Success's line is 10 %: a margin for commands not tuned on)
    + 0.25·smoothness/allowance; on the noisy gyro + 100 per unit of that ratio above
    SMOOTHNESS_CAP (a wall: no step response is bought with motor noise). The allowance is the
    start's smoothness, on the noisy gyro at least `floor_us` (the reference tune's). Infinite where
    an axis leaves more commands never risen than the start did: the start's own are commands
    physics may forbid (`settle_limits`: a yaw whose motors cannot turn it that fast), and were
    they a wall, every candidate would hit it and the search could not move."""
    if (not np.all(np.isfinite(s.error)) or np.any(s.not_risen > ref.not_risen)
            or not math.isfinite(s.smoothness)):
        return float("inf")
    error = 3.0 * s.error.sum() / ref.error.sum()
    both_rose = np.isfinite(s.rise_ms) & np.isfinite(ref.rise_ms)  # an axis on which no command rose: 1
    rise = 0.5 * float(np.sum(np.where(both_rose, s.rise_ms / ref.rise_ms, 1.0)))
    overshoot = 0.05 * float(np.sum(np.maximum(s.peak_pct - np.maximum(ref.peak_pct, 110.0), 0.0)))
    failed = float(np.sum(100.0 - s.success_pct)) / 5.0
    failed += 0.1 * float(np.sum(np.maximum(s.worst_settle_pct - SETTLE_MARGIN_PCT, 0.0)))
    rough = s.smoothness / max(ref.smoothness, floor_us if noisy else 0.0)
    shaking = 0.25 * rough + (100.0 * max(rough - SMOOTHNESS_CAP, 0.0) if noisy else 0.0)
    return float(error + rise + overshoot + failed + shaking)


def reference_roughness(commands: np.ndarray, gyro_noise: float) -> float:
    """The reference tune's motor roughness on its own airframe with the noisy gyro: the floor of
    the noise allowance."""
    from fcemu.training.pid_search import Flights

    flights = Flights(nominal(load_airframe(REFERENCE[0])), commands, gyro_noise)
    return flights.evaluate(load_preset(REFERENCE[1]), True).smoothness


def held_out_steps(opts: TuneOptions, preset: dict[str, Any]) -> Any:
    """Traces of `preset` flown as the check flew it (noise-free gyro) on the held-out commands that
    `evaluation.step_plots` draws, one per axis: the check's workers keep no traces, and three
    flights cost a fraction of a second."""
    from fcemu.evaluation.step_plots import representative_commands
    from fcemu.firmware.pid_controller import PIDRateController
    from fcemu.sim_bridge.twin import Twin
    from fcemu.sitl.traces import Traces
    from fcemu.training.pid_search import DT, fly

    airframe = load_airframe(opts.airframe)
    held_out = episodic_commands(opts.seed + 1, opts.check_episodes)
    commands = held_out[representative_commands(held_out)]
    rate, pwm = fly(PIDRateController.from_dict(preset), Twin(airframe, rig="rig"), commands,
                    airframe.hover_throttle())
    return Traces(np.arange(rate.shape[1]) * DT, np.broadcast_to(commands[:, None, :], rate.shape), rate, pwm,
                  controller="tuned PID", seed=opts.seed + 1)


def _finite(value: float) -> float | None:
    """Rounded for the JSON; None for an infinite cost (a start on which an axis never rises)."""
    return round(value, 4) if math.isfinite(value) else None


def bound_cache_path(rig: Any, commands: np.ndarray, horizon: int) -> Path:
    """Where the bound of these commands on this rig is kept: it depends on nothing else (not on
    the PID), and its programmes cost more than the search on a small machine."""
    from fcemu.evaluation.bound import EPISODE_SAMPLES, tail_axes

    key = hashlib.sha256()
    constants = [rig.kf, rig.w_max, rig.a_up, rig.a_down, rig.dt, horizon, TIGHT_BOUND]
    if tail_axes(rig, horizon):
        constants.append(EPISODE_SAMPLES)  # where the tail ends
    for value in (rig.B, rig.inertia, np.array(constants),
                  np.asarray(commands, dtype=float)):
        key.update(np.ascontiguousarray(value, dtype=float).tobytes())
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return root / "fcemu" / "bound" / f"{key.hexdigest()[:32]}.json"


def cached_bounds(rig: Any, commands: np.ndarray, solve: Any) -> tuple[np.ndarray, float]:
    """(per command [bound, its split over roll, pitch, yaw], the seconds its programmes took): from the
    cache (`bound_cache_path`), or `solve()`'s `evaluation.bound.CommandBound`s, then kept there with
    their time, which a tune charges to its budget either way: the same search, cached or not."""
    from fcemu.evaluation.bound import HORIZON

    cache = bound_cache_path(rig, commands, HORIZON)
    try:
        kept = json.loads(cache.read_text())
        return np.array(kept["per_command"], dtype=float), float(kept["solve_s"])
    except (OSError, ValueError, KeyError, TypeError):
        pass  # none yet, or one written without its time
    t = time.monotonic()
    per_command = np.array([[b.bound, *b.split] for b in solve()])
    solve_s = round(time.monotonic() - t, 1)
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_text(json.dumps({"per_command": per_command.tolist(), "solve_s": solve_s}))
    except OSError:
        pass  # a cache that cannot be written costs the next tune the programmes, nothing else
    return per_command, solve_s


class Tuner:
    """One tune: the physics start, the bound on the held-out commands, two search stages, the check."""

    def __init__(self, opts: TuneOptions, log: Any = None) -> None:
        self.opts = opts
        self.log = log or (lambda line: None)
        self.t0 = time.monotonic()
        self.airframe = load_airframe(opts.airframe)
        reference = load_preset(REFERENCE[1])
        self.ref_physics = loop_physics(load_airframe(REFERENCE[0]), QuadXMixer(**reference["mixer"]))
        self.physics = loop_physics(self.airframe, QuadXMixer(**mixer_for(reference, self.airframe)))
        self.start = iris_tune_carried_over(self.airframe)
        self.knobs = knobs_for(self.ref_physics, self.physics, reference)
        self.tuning = episodic_commands(opts.seed, opts.episodes)
        self.held_out = episodic_commands(opts.seed + 1, opts.check_episodes)
        # The budget is the whole tune's. The bound's solve time is charged to it whether solved now or
        # read from the cache, so a cached bound leaves the search no more time than a fresh one.
        self.budget_t0: float | None = None
        self.search_s = opts.budget_s

    def elapsed(self) -> float:
        return time.monotonic() - self.t0

    def say(self, stage: str, text: str) -> None:
        if self.budget_t0 is None:
            self.log(f"[{self.elapsed():5.0f} s] {stage}: {text}")
        else:
            spent = time.monotonic() - self.budget_t0 + self.opts.budget_s - self.search_s
            self.log(f"[{spent:5.0f}/{self.opts.budget_s:.0f} s] {stage}: {text}")

    def run(self) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
        """(the tuned preset, the tuning record, the held-out check)."""
        with CandidatePool(self.airframe, self.opts.gyro_noise, self.opts.jobs) as pool:
            bound = self.bound(pool)
            budget = self.opts.budget_s
            self.search_s = max(budget - bound["charged_s"], LEAST_SEARCH_SHARE * budget)
            self.budget_t0 = time.monotonic()
            tuned, record = self.search(pool, self.budget_t0)
            return tuned, record, self.check(pool, tuned, bound)

    def bound(self, pool: CandidatePool) -> dict[str, Any]:
        """The lower bound on the Error over the held-out commands (first: its time is then known)."""
        from fcemu.evaluation.bound import HORIZON, rig_constants

        t = time.monotonic()
        try:
            rig = rig_constants(self.airframe)
        except UserError as exc:
            return {"bound": None, "bound_refused": str(exc), "wall_s": 0.0, "charged_s": 0.0}
        n = len(self.held_out)
        every = max(1, n // 5)

        def solve() -> list[Any]:
            self.say("bound", f"solving {n} linear programmes: the floor under the held-out Error")
            return pool.bounds(self.held_out, lambda done: done % every == 0 and done < n and self.say(
                "bound", f"{done}/{n} held-out commands"), tight=TIGHT_BOUND)

        per_command, solve_s = cached_bounds(rig, self.held_out, solve)
        total, split = float(per_command[:, 0].mean()), per_command[:, 1:].mean(axis=0)
        self.say("bound", f"{total:.1f} on {len(per_command)} held-out commands (seed {self.opts.seed + 1})")
        return {"bound": {"sum": round(total, 2), "horizon": HORIZON, "split_at_optimum": per_axis(split)},
                "wall_s": round(time.monotonic() - t, 1), "charged_s": solve_s}

    def search(self, pool: CandidatePool, budget_t0: float) -> tuple[dict[str, Any], dict[str, Any]]:
        o = self.opts
        stages: list[dict[str, Any]] = []
        scores: dict[str, Any] = {}
        best = self.start
        end = None
        for name, noisy, share in (("clean", False, 0.55), ("noisy_gyro", True, 1.0)):
            t_stage = time.monotonic()
            ref = pool.scores([self.start], noisy, self.tuning)[0]
            if end is None:  # keep time for the check's five flights of the held-out commands
                flight_s = time.monotonic() - t_stage
                check_s = 3.0 + flight_s * o.check_episodes / o.episodes * 5 / min(o.jobs, 5)
                end = budget_t0 + self.search_s - check_s
            found = ref if best is self.start else pool.scores([best], noisy, self.tuning)[0]
            floor = reference_roughness(self.tuning, o.gyro_noise) if noisy else 0.0
            state = SearchState(best, found, cost(found, ref, noisy, floor))
            deadline = t_stage + share * max(end - t_stage, 0.0)
            self.say(name, f"start cost {state.cost:.4f} ({ref.line()})")
            state = pattern_search(state, self.knobs, pool, noisy, self.tuning,
                                   lambda s, r=ref, n=noisy, f=floor: cost(s, r, n, f), deadline, o.rounds,
                                   progress=lambda line, n=name: self.say(n, line), label=name)
            best = state.preset
            self.say(name, f"done: cost {state.cost:.4f} after {state.evaluations} flights of "
                           f"{o.episodes} commands ({state.score.line()})")
            stages.append({"stage": name, "gyro_noise": o.gyro_noise if noisy else 0.0,
                           "start_cost": _finite(cost(ref, ref, noisy, floor)), "cost": _finite(state.cost),
                           "reference_smoothness_us": round(floor, 3) if noisy else None,
                           "evaluations": state.evaluations, "rounds": state.rounds,
                           "wall_s": round(time.monotonic() - t_stage, 1)})
            scores[name] = {"start": ref.to_json(), "tuned": state.score.to_json()}
        return best, {"seed": o.seed, "episodes": o.episodes, "stages": stages, "tuning_set": scores}

    def check(self, pool: CandidatePool, tuned: dict[str, Any], bound: dict[str, Any]) -> dict[str, Any]:
        """Held-out commands (seed + 1): the tuned PID, clean and noisy, the start and the Iris PID,
        against the lower bound on the Error; which lines are met."""
        t_check = time.monotonic()
        cmds = self.held_out
        tuned_s, start_s, iris_s = pool.scores([tuned, self.start, load_preset("iris")], False, cmds)
        noisy_tuned, noisy_start = pool.scores([tuned, self.start], True, cmds)
        self.say("check", f"held out, tuned: {tuned_s.line()}")
        out: dict[str, Any] = {"seed": self.opts.seed + 1, "episodes": len(cmds), "tuned": tuned_s.to_json(),
                               "tuned_noisy_gyro": noisy_tuned.to_json(), "start": start_s.to_json(),
                               "start_noisy_gyro": noisy_start.to_json(), "pid_iris": iris_s.to_json(),
                               **{k: v for k, v in bound.items() if k not in ("wall_s", "charged_s")}}
        if out["bound"] is not None:
            for name, s in (("tuned", tuned_s), ("start", start_s), ("pid_iris", iris_s)):
                out[name]["times_bound"] = round(float(s.error.sum()) / out["bound"]["sum"], 4)
        times = out["tuned"].get("times_bound")
        allowance = max(noisy_start.smoothness, reference_roughness(cmds, self.opts.gyro_noise))
        out["noise_allowance_us"] = round(allowance, 3)
        rough = noisy_tuned.smoothness / allowance
        out["lines"] = {
            "error_times_bound": {"value": times, "line": TIMES_BOUND_LINE,
                                  "met": None if times is None else times <= TIMES_BOUND_LINE},
            "success_pct": {"value": out["tuned"]["success_pct"], "line": SUCCESS_LINE,
                            "met": bool(np.all(tuned_s.success_pct >= SUCCESS_LINE))},
            "smoothness_noisy_gyro_vs_allowance": {"value": round(rough, 3), "line": SMOOTHNESS_CAP,
                                               "met": bool(rough <= SMOOTHNESS_CAP + 1e-9)},
        }
        out["meets_lines"] = all(v["met"] for v in out["lines"].values())
        out["settle_limits"] = settle_limits(self.airframe, cmds)
        out["wall_s"] = {"bound": bound["wall_s"], "bound_charged": bound["charged_s"],
                         "flights": round(time.monotonic() - t_check, 1)}
        return out
