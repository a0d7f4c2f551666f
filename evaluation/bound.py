"""A lower bound on the Error any rate controller can reach on the twin: `fcemu bound`.

    fcemu bound --episodes 1000 --seed 7 --controller pid --controller policies/iris_rate_ppo.onnx

Issue 5 asks for a policy whose Error sum is ≤ 0.8 × the tuned PID's. This asks what the
physics allows: for each episodic command (the evaluator's, `sim_bridge.tasks`), a linear
programme finds the smallest Σₖ|Ω* − Ω(k)| over any sequence of rotor speeds the motors can
follow. No controller, learned or not, does better on the ball-joint twin, because every
constraint below holds for every trajectory the twin can fly (tests/evaluation/test_bound.py
checks this against trajectories flown by the twin itself):

- Rotor speed ωᵢ (`sim_bridge.plant.MotorModel`'s first-order lag, the twin's): from 0 at t = 0,
  (1 − a_down)·ωᵢ(k−1) ≤ ωᵢ(k) ≤ ωᵢ(k−1) + a_up·(ω_max − ωᵢ(k−1)), 0 ≤ ωᵢ ≤ ω_max.
- Thrust Tᵢ = k_F·ωᵢ², relaxed to its convex hull on the speeds reachable by step k
  (tangent cuts below, the secant k_F·W_k·ωᵢ above, W_k the fastest spin-up's speed), plus
  its own rate limits: Tᵢ(k) − Tᵢ(k−1) ≤ T_max·a_up/(2 − a_up) (the largest one-step rise
  of k_F·ω²) and Tᵢ(k) ≥ (1 − a_down)²·Tᵢ(k−1).
- Body rates: the twin's semi-implicit Euler step Ω(k+1) = Ω(k) + dt·B·T(k), with B the
  angular acceleration per newton of each motor read from the MuJoCo model, and the gyro's
  one-step delay as the evaluation's traces record it.

Every relaxation is in the controller's favour: the motors are independent (the `throttle`
mapping and the PID's mixer tie their mean to the collective), the controller knows the
command and the state exactly (no sensor delay, no observation to infer them from), and
the horizon ends at `horizon` steps (later error counts as zero). One approximation: the
gyroscopic term −I⁻¹(Ω × IΩ) is left out of the bound. `gyro_passes` re-solves with it
taken from the previous solution's trajectory (a self-consistent estimate of its effect,
not a bound), so a reader can see how much it moves the figure.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import time
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy import sparse
from scipy.optimize import linprog
from tqdm import tqdm

from sim_bridge.airframe import FLU_FROM_FRD, load_airframe
from sim_bridge.tasks import episodic_commands
from sim_bridge.twin import Twin

HORIZON = 400  # steps: the error left after 0.4 s is a few % of an episode's
TANGENTS = np.linspace(0.1, 1.0, 10)  # fractions of ω_max where k_F·ω² is cut from below


@dataclass(frozen=True)
class RigConstants:
    B: np.ndarray  # (3, 4) FRD rad/s² per newton of each motor's thrust
    inertia: np.ndarray  # (3,) the rig's principal moments (kg·m², diagonal mass matrix)
    kf: float  # the motor model's (sim_bridge.plant.MotorModel)
    w_max: float
    a_up: float
    a_down: float
    dt: float


def rig_constants(airframe: str = "iris", dt: float = 0.001) -> RigConstants:
    af = load_airframe(airframe)
    twin = Twin(af, "rig", None, dt)
    m, d = twin.model, twin.data
    B = np.zeros((3, 4))
    for i in range(4):  # ctrl is each motor's thrust (N); qacc at rest is M⁻¹·torque
        mujoco.mj_resetData(m, d)
        d.ctrl[:] = 0.0
        d.ctrl[i] = 1.0
        mujoco.mj_forward(m, d)
        B[:, i] = d.qacc[:3] * FLU_FROM_FRD
    M = np.zeros((3, 3))
    mujoco.mj_fullM(m, d, M)
    if np.abs(M - np.diag(np.diag(M))).max() > 1e-12:
        raise ValueError("the rig's mass matrix is not diagonal; the gyroscopic estimate assumes it is")
    mo = twin.motors
    return RigConstants(B, np.diag(M).copy(), mo.kf, mo.max_rotor_speed, mo.alpha_up, mo.alpha_down, dt)


class ErrorBound:
    """The linear programme for one horizon; `solve(command)` returns the per-axis bound."""

    def __init__(self, c: RigConstants, horizon: int = HORIZON) -> None:
        self.c, self.K = c, horizon
        K = horizon
        # Variable blocks: ω (4K), T (4K), Ω after step k (3K), slack s ≥ |Ω* − rate| (3K).
        self.n_w, self.n_t, self.n_o, self.n_s = 4 * K, 4 * K, 3 * K, 3 * K
        self.off_t = self.n_w
        self.off_o = self.off_t + self.n_t
        self.off_s = self.off_o + self.n_o
        self.n = self.off_s + self.n_s
        self._build()

    def w(self, i: int, k: int) -> int:
        return i * self.K + k

    def t(self, i: int, k: int) -> int:
        return self.off_t + i * self.K + k

    def o(self, j: int, k: int) -> int:
        return self.off_o + j * self.K + k

    def s(self, j: int, k: int) -> int:
        return self.off_s + j * self.K + k

    def _build(self) -> None:
        c, K = self.c, self.K
        rows, cols, vals, ub = [], [], [], []
        eq_rows, eq_cols, eq_vals = [], [], []
        r = 0

        def add(entries: list[tuple[int, float]], bound: float) -> None:
            nonlocal r
            for col, v in entries:
                rows.append(r)
                cols.append(col)
                vals.append(v)
            ub.append(bound)
            r += 1

        t_max = c.kf * c.w_max**2
        rise = t_max * c.a_up / (2.0 - c.a_up)
        decay = (1.0 - c.a_down) ** 2
        for i in range(4):
            for k in range(K):
                w, t = self.w(i, k), self.t(i, k)
                reach = c.w_max * (1.0 - (1.0 - c.a_up) ** (k + 1))
                if k == 0:
                    add([(w, 1.0)], c.a_up * c.w_max)
                else:
                    wp, tp = self.w(i, k - 1), self.t(i, k - 1)
                    add([(w, 1.0), (wp, -(1.0 - c.a_up))], c.a_up * c.w_max)
                    add([(wp, 1.0 - c.a_down), (w, -1.0)], 0.0)
                    add([(t, 1.0), (tp, -1.0)], rise)
                    add([(tp, decay), (t, -1.0)], 0.0)
                for f in TANGENTS:  # T ≥ k_F·(2·w_j·ω − w_j²)
                    wj = f * c.w_max
                    add([(w, 2.0 * c.kf * wj), (t, -1.0)], c.kf * wj * wj)
                add([(t, 1.0), (w, -c.kf * reach)], 0.0)  # T ≤ k_F·W_k·ω
        # Ω(k) after step k: Ω(0) = dt·B·T(0), Ω(k) = Ω(k−1) + dt·B·T(k).
        e = 0
        for j in range(3):
            for k in range(K):
                eq_rows.append(e)
                eq_cols.append(self.o(j, k))
                eq_vals.append(1.0)
                if k > 0:
                    eq_rows.append(e)
                    eq_cols.append(self.o(j, k - 1))
                    eq_vals.append(-1.0)
                for i in range(4):
                    eq_rows.append(e)
                    eq_cols.append(self.t(i, k))
                    eq_vals.append(-c.dt * c.B[j, i])
                e += 1
        # The evaluation's rate sample k is the gyro before step k−1's integration:
        # rate[0] = rate[1] = 0 and rate[k] = Ω(k−2) for k ≥ 2. Slack rows: ±(Ω* − Ω) ≤ s.
        self.n_motor_rows = r
        for j in range(3):
            for k in range(K - 2):
                add([(self.o(j, k), -1.0), (self.s(j, k + 2), -1.0)], 0.0)  # Ω* − Ω ≤ s (bound set later)
                add([(self.o(j, k), 1.0), (self.s(j, k + 2), -1.0)], 0.0)  # Ω − Ω* ≤ s
        self.A_ub = sparse.csr_matrix((vals, (rows, cols)), shape=(r, self.n))
        self.b_ub = np.array(ub)
        self.A_eq = sparse.csr_matrix((eq_vals, (eq_rows, eq_cols)), shape=(e, self.n))
        self.b_eq = np.zeros(e)
        self.cost = np.zeros(self.n)  # Σ of the slacks from sample 2 on (samples 0 and 1 are at rest)
        for j in range(3):
            self.cost[self.s(j, 2):self.s(j, K - 1) + 1] = 1.0
        self.bounds = ([(0.0, c.w_max)] * self.n_w + [(0.0, t_max)] * self.n_t
                       + [(None, None)] * self.n_o + [(0.0, None)] * self.n_s)

    def solve(self, command: np.ndarray, gyro_passes: int = 0) -> np.ndarray:
        """Per-axis lower bound on Σₖ|Ω* − rate(k)| for k < horizon, for a held command (FRD rad/s).

        `gyro_passes` > 0 re-solves with the gyroscopic acceleration −I⁻¹(Ω × IΩ) of the
        previous solution's trajectory added to the dynamics (an estimate of what leaving it
        out changes, not part of the bound).
        """
        K = self.K
        b_ub = self.b_ub.copy()
        # Slack rows come in pairs per (axis, sample): Ω* − Ω ≤ s, then Ω − Ω* ≤ s.
        pairs = b_ub[self.n_motor_rows:].reshape(3, K - 2, 2)
        pairs[..., 0] = -np.asarray(command, dtype=float)[:, None]
        pairs[..., 1] = np.asarray(command, dtype=float)[:, None]
        b_eq = self.b_eq.copy()
        for _ in range(gyro_passes + 1):
            res = linprog(self.cost, A_ub=self.A_ub, b_ub=b_ub, A_eq=self.A_eq, b_eq=b_eq,
                          bounds=self.bounds, method="highs")
            if res.status != 0:
                raise RuntimeError(f"LP for command {command} failed: {res.message}")
            rates = res.x[self.off_o:self.off_s].reshape(3, K).T  # Ω(k), FRD
            before = np.vstack([np.zeros(3), rates[:-1]])  # Ω(k−1): the twin's step uses the old rate
            inertia = self.c.inertia
            gyro = -np.cross(before, before * inertia) / inertia
            b_eq = (self.c.dt * gyro).T.reshape(-1)  # rows j·K + k: Ω(k) − Ω(k−1) − dt·B·T(k) = dt·g
        slack = res.x[self.off_s:].reshape(3, K)
        return slack[:, 2:].sum(axis=1) + 2.0 * np.abs(command)  # samples 0 and 1 sit at rest


_WORKER: ErrorBound | None = None


def _init_worker(horizon: int) -> None:
    global _WORKER
    _WORKER = ErrorBound(rig_constants(), horizon)


def _solve(job: tuple[np.ndarray, int]) -> np.ndarray:
    assert _WORKER is not None
    command, passes = job
    return _WORKER.solve(command, passes)


def error_bounds(commands: np.ndarray, horizon: int = HORIZON, gyro_passes: int = 0, jobs: int = 1,
                 progress: bool = False) -> np.ndarray:
    """The per-axis bound for each command, (n, 3); `jobs` worker processes."""
    work = [(np.asarray(cmd, dtype=float), gyro_passes) for cmd in commands]
    if jobs <= 1:
        _init_worker(horizon)
        return np.array([_solve(w) for w in tqdm(work, desc="bound (LP per command)", disable=not progress)])
    with mp.get_context("spawn").Pool(jobs, _init_worker, (horizon,)) as pool:
        it = pool.imap(_solve, work)
        return np.array(list(tqdm(it, total=len(work), desc="bound (LP per command)", disable=not progress)))


def bound_command(args) -> int:
    """`fcemu bound`: the bound on the evaluator's commands, and each --controller's Error against it."""
    import sys

    from evaluation.metrics import AXES, compute_metrics
    from evaluation.runner import EvalConfig, run_controller

    progress = sys.stderr.isatty() and not args.json
    commands = episodic_commands(args.seed, args.episodes)
    t0 = time.perf_counter()
    bounds = error_bounds(commands, args.horizon, args.gyro_passes, args.jobs or mp.cpu_count(), progress)
    per_axis = bounds.mean(axis=0)
    out: dict = {"episodes": args.episodes, "seed": args.seed, "horizon": args.horizon,
                 "gyro_passes": args.gyro_passes,
                 "bound": {a: round(float(v), 2) for a, v in zip(AXES, per_axis, strict=True)},
                 "bound_sum": round(float(per_axis.sum()), 2), "wall_s": round(time.perf_counter() - t0, 1),
                 "controllers": []}
    cfg = EvalConfig(task="episodic", episodes=args.episodes, seed=args.seed)
    for spec in args.controller or []:
        m = compute_metrics(run_controller(spec, cfg, progress=progress))
        error = {a: round(m.stat("error", a).mean, 2) for a in AXES}
        total = sum(error.values())
        out["controllers"].append({"controller": spec, "error": error, "error_sum": round(total, 2),
                                   "times_bound": round(total / out["bound_sum"], 4)})
    if args.json:
        print(json.dumps(out))
        return 0
    kind = f"; gyroscopic term estimated ({args.gyro_passes} passes)" if args.gyro_passes else ""
    print(f"lower bound on the Error, {args.episodes} commands (seed {args.seed}), "
          f"horizon {args.horizon} steps{kind}: " + "/".join(f"{v:.1f}" for v in per_axis)
          + f" (sum {per_axis.sum():.1f})")
    for c in out["controllers"]:
        print(f"{c['controller']:>32}: error " + "/".join(f"{v:.1f}" for v in c["error"].values())
              + f" (sum {c['error_sum']:.1f}) = {c['times_bound']:.3f} × the bound")
    return 0
