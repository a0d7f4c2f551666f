"""A near-optimal open-loop flight of one episodic command: how far above the bound the twin can fly.

Sequential linear programming on the twin's own model: the motors' lag exactly, the thrust
k_F·ω² and the gyroscopic products linearised about the previous iterate inside a trust
region that shrinks each pass. `pwm_for_speeds` turns its rotor speeds into the PWM that
makes the motor model follow them, and `fly` flies that PWM on the twin from rest. The
least Error any controller can reach on the command lies between `fcemu bound` and what
this flight scores, over the same horizon. It is a controller that knows the command in
advance and plans the whole episode, which a feedback controller cannot; the tests use it
as the strongest flight they have against the bound.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.optimize import linprog

from fcemu.evaluation.rate_boxes import GYRO_PAIRS, RigConstants, gyro_coefficients
from fcemu.sim_bridge.env_config import DEFAULT_AIRFRAME
from fcemu.sim_bridge.twin import Twin


def pwm_for_speeds(c: RigConstants, speeds: np.ndarray, pwm_min: float = 1000.0,
                   pwm_max: float = 2000.0) -> np.ndarray:
    """The PWM (K, 4) under which the motor model, from rest, runs at `speeds` (K, 4) step by step."""
    pwm = np.zeros_like(speeds)
    before = np.zeros(4)
    for k, target in enumerate(speeds):
        gap = target - before
        alpha = np.where(gap > 0.0, c.a_up, c.a_down)
        command = np.clip(before + gap / alpha, 0.0, c.w_max)
        pwm[k] = pwm_min + command * (pwm_max - pwm_min) / c.w_max
        before = before + alpha * (command - before)
    return pwm


def fly(pwm: np.ndarray, airframe: str = DEFAULT_AIRFRAME, dt: float = 0.001) -> np.ndarray:
    """Fly `pwm` (K, 4) on the ball-joint twin from rest; the rate samples (K, 3) the evaluator records."""
    twin = Twin(airframe, "rig", None, dt)
    rates = [twin.reset().gyro]
    for p in pwm[:-1]:
        rates.append(twin.step(p).gyro)
    return np.array(rates)


def horizon_error(command: np.ndarray, rates: np.ndarray) -> float:
    return float(np.abs(np.asarray(command) - rates).sum())


def near_optimal_pwm(c: RigConstants, command: np.ndarray, horizon: int, passes: int = 12,
                     airframe: str = DEFAULT_AIRFRAME, through: tuple[int, int, float, float] | None = None,
                     ) -> tuple[np.ndarray, float]:
    """PWM (horizon, 4) from sequential linear programming, and its flown Error over the horizon.

    `through` = (axis, step k, rate v, side ±1) asks for side·Ω_axis(k) ≥ side·v on the way:
    the least Error of a flight that passes beyond v at step k.
    """
    K = horizon
    command = np.asarray(command, dtype=float)
    coeff = gyro_coefficients(c.inertia)
    n_w, n_o = 4 * K, 3 * K
    n = n_w + 2 * n_o
    k = np.arange(K)
    # Motor rows (exact): ω(k) ≤ ω(k−1) + a_up·(ω_max − ω(k−1)), ω(k) ≥ (1 − a_down)·ω(k−1).
    rows, cols, vals, ub = [], [], [], []
    for i in range(4):
        w = i * K + k
        base = len(ub) + k
        rows += [base, base[1:]]
        cols += [w, w[:-1]]
        vals += [np.ones(K), np.full(K - 1, -(1.0 - c.a_up))]
        ub += [c.a_up * c.w_max] * K
        base = len(ub) + k[:-1]
        rows += [base, base]
        cols += [w[:-1], w[1:]]
        vals += [np.full(K - 1, 1.0 - c.a_down), -np.ones(K - 1)]
        ub += [0.0] * (K - 1)
    # Error slacks: ±(Ω* − Ω(k)) ≤ s(k + 2).
    for j in range(3):
        o, s = n_w + j * K + k[:-2], n_w + n_o + j * K + k[:-2] + 2
        for sign in (-1.0, 1.0):
            base = len(ub) + k[:-2]
            rows += [base, base]
            cols += [o, s]
            vals += [np.full(K - 2, sign), -np.ones(K - 2)]
            ub += [sign * command[j]] * (K - 2)
    if through is not None:
        axis, step, rate, side = through
        rows.append(np.array([len(ub)]))
        cols.append(np.array([n_w + axis * K + step]))
        vals.append(np.array([-float(side)]))
        ub.append(-side * rate)
    A_ub = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(len(ub), n))
    cost = np.zeros(n)
    for j in range(3):
        cost[n_w + n_o + j * K + 2:n_w + n_o + (j + 1) * K] = 1.0
    speeds = np.outer(c.w_max * (1.0 - (1.0 - c.a_up) ** (k + 1)), np.full(4, 0.7))  # (K, 4)
    rates = np.zeros((K, 3))
    radius = 0.3 * c.w_max
    best = (np.inf, pwm_for_speeds(c, speeds))
    for _ in range(passes):
        A_eq, b_eq = _dynamics(c, coeff, speeds, rates, n)
        lo, hi = np.maximum(speeds - radius, 0.0), np.minimum(speeds + radius, c.w_max)
        bounds = np.vstack([np.stack([lo.T.ravel(), hi.T.ravel()], axis=1),
                            np.tile([-np.inf, np.inf], (n_o, 1)), np.tile([0.0, np.inf], (n_o, 1))])
        res = linprog(cost, A_ub=A_ub, b_ub=np.array(ub), A_eq=A_eq, b_eq=b_eq, bounds=bounds, method="highs")
        if res.status != 0:
            radius *= 0.5
            continue
        speeds = res.x[:n_w].reshape(4, K).T
        rates = res.x[n_w:n_w + n_o].reshape(3, K).T
        radius = max(0.6 * radius, 0.005 * c.w_max)
        pwm = pwm_for_speeds(c, speeds)
        flown = horizon_error(command, fly(pwm, airframe, c.dt))
        if flown < best[0]:
            best = (flown, pwm)
    return best[1], best[0]


def _dynamics(c: RigConstants, coeff: np.ndarray, speeds: np.ndarray, rates: np.ndarray,
              n: int) -> tuple[sparse.csr_matrix, np.ndarray]:
    """Ω(k) − Ω(k−1) = dt·(B·k_F·ω² + g(Ω(k−1))), both linearised about `speeds` (K, 4) and `rates` (K, 3)."""
    K = len(speeds)
    n_w = 4 * K
    k = np.arange(K)
    before = np.vstack([np.zeros(3), rates[:-1]])
    rows, cols, vals = [], [], []
    rhs = np.zeros((3, K))
    for j, (a, b) in enumerate(GYRO_PAIRS):
        row = j * K + k
        rows += [row, row[1:], row[1:], row[1:]]
        cols += [n_w + j * K + k, n_w + j * K + k[:-1], n_w + a * K + k[:-1], n_w + b * K + k[:-1]]
        gain = -c.dt * coeff[j]  # w ≈ b̂·Ω_a + â·Ω_b − â·b̂ about the previous rates
        vals += [np.ones(K), -np.ones(K - 1), gain * before[1:, b], gain * before[1:, a]]
        rhs[j] = -c.dt * coeff[j] * before[:, a] * before[:, b]
        for i in range(4):  # k_F·ω² ≈ k_F·(2·ŵ·ω − ŵ²)
            rows.append(row)
            cols.append(i * K + k)
            vals.append(-c.dt * c.B[j, i] * c.kf * 2.0 * speeds[:, i])
            rhs[j] -= c.dt * c.B[j, i] * c.kf * speeds[:, i] ** 2
    A = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(3 * K, n))
    return A, rhs.ravel()
