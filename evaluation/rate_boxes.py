"""Boxes on the body rates that every low-Error trajectory stays in, for `evaluation.bound`.

The bound's linear programme relaxes the gyroscopic acceleration g_j = c_j·Ω_a·Ω_b (the
twin's −I⁻¹(Ω × IΩ)) by McCormick's envelope of each product, which holds for every
trajectory whose rates stay in the boxes it is built on. This module finds boxes that
provably hold every trajectory whose Error over the horizon is at most `cap` (the bound
is then min(LP, cap): a trajectory above the cap is above the bound anyway).

The proof is a first exit. Let a trajectory with Error ≤ cap leave a box B for the first
time at step k0, axis j, at rate v. Up to k0 every rate was inside B, so each step's
acceleration lay in the range the motors (thrust 0 … the fastest spin-up's) and the
gyroscopic products over B allow; that bounds how fast Ω_j could have climbed to v and,
with the boxes that hold after the exit, how fast it can leave it. Summing each sample's
least distance from the command under those limits gives the least Error of axis j
(`exit_error`); the other axes cost at least `others[j]`. Where the two exceed the
cap for every v past a box edge, no trajectory under the cap crosses it: that edge holds.
`_certify` starts from a box it checks this way and tightens it, each step valid given the
last. Two rounds: a crude box from interval reachability alone (`crude`), then a tighter
one (`refine`) once the crude box has let a linear programme bound the other axes' Error.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

GYRO_PAIRS = ((1, 2), (0, 2), (0, 1))  # g_roll ∝ q·r, g_pitch ∝ p·r, g_yaw ∝ p·q
HUGE = 1e6  # rad/s: stands for "unbounded" in interval arithmetic (its square stays finite)
START_LIMITS = (15.0, 25.0, 40.0, 60.0, 100.0)  # rad/s: |Ω| caps tried as the crude box's start
BISECTIONS = 16
EDGE = 1e-7  # rad/s: "just past" a box edge


@dataclass(frozen=True)
class RigConstants:
    B: np.ndarray  # (3, 4) FRD rad/s² per newton of each motor's thrust
    inertia: np.ndarray  # (3,) the rig's principal moments (kg·m², diagonal mass matrix)
    kf: float  # the motor model's (sim_bridge.plant.MotorModel)
    w_max: float
    a_up: float
    a_down: float
    dt: float


@dataclass(frozen=True)
class Boxes:
    """Per step k, lo ≤ Ω(k) ≤ hi, (K, 3) FRD rad/s; Ω(k) is the rate after step k."""

    lo: np.ndarray
    hi: np.ndarray

    def __getitem__(self, steps: slice) -> Boxes:
        return Boxes(self.lo[steps], self.hi[steps])

    @property
    def empty(self) -> bool:
        return bool((self.lo > self.hi).any())

    def contains(self, rates: np.ndarray, tol: float = 1e-9) -> bool:
        n = len(rates)
        return bool((rates >= self.lo[:n] - tol).all() and (rates <= self.hi[:n] + tol).all())


def gyro_coefficients(inertia: np.ndarray) -> np.ndarray:
    """c with g_j = c_j·Ω_a·Ω_b (`GYRO_PAIRS`): −I⁻¹(Ω × IΩ) for a diagonal inertia."""
    ix, iy, iz = inertia
    return np.array([-(iz - iy) / ix, -(ix - iz) / iy, -(iy - ix) / iz])


def product_range(lo: np.ndarray, hi: np.ndarray, coeff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Range of coeff_j·Ω_a·Ω_b over boxes (..., 3) → (..., 3) lo, hi."""
    out_lo, out_hi = np.empty_like(lo), np.empty_like(hi)
    for j, (a, b) in enumerate(GYRO_PAIRS):
        corners = np.stack([lo[..., a] * lo[..., b], lo[..., a] * hi[..., b],
                            hi[..., a] * lo[..., b], hi[..., a] * hi[..., b]]) * coeff[j]
        out_lo[..., j], out_hi[..., j] = corners.min(axis=0), corners.max(axis=0)
    return out_lo, out_hi


def _dist(command: np.ndarray | float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Least |command − x| over x in [lo, hi]."""
    return np.maximum(0.0, np.maximum(lo - command, command - hi))


class RateBoxes:
    """Box certification for one rig and horizon; `crude` then `refine` per command."""

    def __init__(self, c: RigConstants, horizon: int) -> None:
        self.c, self.K = c, horizon
        self.n_err = horizon - 2  # Ω(0 … K−3) are the error samples 2 … K−1; samples 0, 1 sit at rest
        self.coeff = gyro_coefficients(c.inertia)
        k = np.arange(horizon)
        fastest = c.kf * (c.w_max * (1.0 - (1.0 - c.a_up) ** (k + 1))) ** 2  # thrust ceiling at step k
        self.motor_lo = fastest[:, None] * np.clip(c.B, None, 0.0).sum(axis=1)
        self.motor_hi = fastest[:, None] * np.clip(c.B, 0.0, None).sum(axis=1)
        self.reach = self.reachable()  # holds for every trajectory from rest
        self.reach_accel = self.accel(self.reach)

    def accel(self, box: Boxes) -> tuple[np.ndarray, np.ndarray]:
        """Acceleration range of each step k (K, 3) while Ω(k−1) is in `box` (step 0 starts at rest)."""
        g_lo, g_hi = product_range(box.lo[:-1], box.hi[:-1], self.coeff)
        zero = np.zeros((1, 3))
        return self.motor_lo + np.vstack([zero, g_lo]), self.motor_hi + np.vstack([zero, g_hi])

    def reachable(self, box: Boxes | None = None) -> Boxes:
        """Where Ω(k) can be, from rest, by interval arithmetic; intersected with `box` if given."""
        lo, hi = np.zeros((self.K, 3)), np.zeros((self.K, 3))
        p_lo, p_hi = np.zeros(3), np.zeros(3)
        dt = self.c.dt
        for k in range(self.K):
            g_lo, g_hi = product_range(p_lo, p_hi, self.coeff) if k else (0.0, 0.0)
            p_lo = np.maximum(p_lo + dt * (self.motor_lo[k] + g_lo), -HUGE)
            p_hi = np.minimum(p_hi + dt * (self.motor_hi[k] + g_hi), HUGE)
            if box is not None:
                p_lo, p_hi = np.maximum(p_lo, box.lo[k]), np.minimum(p_hi, box.hi[k])
            lo[k], hi[k] = p_lo, p_hi
        return Boxes(lo, hi)

    def forced_error(self, command: np.ndarray, box: Boxes) -> np.ndarray:
        """Per axis, the least Error (samples 0 … K−1) of a trajectory whose rates stay in `box`."""
        return _dist(command, box.lo[:self.n_err], box.hi[:self.n_err]).sum(axis=0) + 2.0 * np.abs(command)

    def crude(self, command: np.ndarray, cap: float) -> Boxes | None:
        """Boxes every trajectory with Error ≤ cap stays in, from reachability alone (None: none proven)."""
        forced = self.forced_error(command, self.reach)
        others = forced.sum() - forced
        for limit in START_LIMITS:
            start = Boxes(np.maximum(self.reach.lo, -limit), np.minimum(self.reach.hi, limit))
            box = self._certify(command, cap, start, others, self.reach, self.reach_accel)
            if box is not None:
                return box
        return None

    def refine(self, command: np.ndarray, cap: float, crude: Boxes, others: np.ndarray) -> Boxes:
        """Tighter boxes, given `others[j]` ≤ the Error of the axes but j of every trajectory in `crude`."""
        box = self._certify(command, cap, crude, others, crude, self.accel(crude), checked=True)
        assert box is not None
        return box

    def _certify(self, command: np.ndarray, cap: float, start: Boxes, others: np.ndarray, after: Boxes,
                 after_accel: tuple[np.ndarray, np.ndarray], checked: bool = False,
                 rounds: int = 12, tol: float = 1e-2) -> Boxes | None:
        """Tighten `start` to a fixed point of the first-exit argument (module docstring).

        `after` (with its acceleration range `after_accel`) holds every trajectory under the
        cap at every step, exit or not; `others[j]` bounds the other axes' Error. Unless
        `checked` (start already proven), `start` must pass the argument on its own: no edge
        a trajectory under the cap could cross. Each later box is valid given the one before.
        """
        box = start
        for n in range(rounds):
            new, crossable = self._tighten(command, cap, box, others, after, after_accel)
            if n == 0 and crossable and not checked:
                return None
            shrink = max(float((new.lo - box.lo).max()), float((box.hi - new.hi).max()))
            box = new
            if shrink < tol or box.empty:
                break
        return box

    def _tighten(self, command: np.ndarray, cap: float, box: Boxes, others: np.ndarray, after: Boxes,
                 after_accel: tuple[np.ndarray, np.ndarray]) -> tuple[Boxes, bool]:
        """box ∩ where no first exit from `box` keeps the Error under the cap; and whether some
        edge of `box` could be crossed under the cap (then `box` itself is not proven)."""
        inside = self.reachable(box)
        a_lo, a_hi = self.accel(box)
        lo, hi = inside.lo.copy(), inside.hi.copy()
        dt = self.c.dt
        crossable = False
        for j in range(3):
            budget = cap - others[j]
            up, open_up = _exit_thresholds(command[j], budget, inside.lo[:, j], inside.hi[:, j],
                                           a_hi[:, j] * dt, after.lo[:, j], after.hi[:, j],
                                           after_accel[0][:, j] * dt, self.n_err)
            down, open_down = _exit_thresholds(-command[j], budget, -inside.hi[:, j], -inside.lo[:, j],
                                               -a_lo[:, j] * dt, -after.hi[:, j], -after.lo[:, j],
                                               -after_accel[1][:, j] * dt, self.n_err)
            hi[:, j] = np.minimum(hi[:, j], up)
            lo[:, j] = np.maximum(lo[:, j], -down)
            crossable |= bool(open_up.any() or open_down.any())
        return Boxes(lo, hi), crossable


def exit_error(command: float, lo: np.ndarray, hi: np.ndarray, rise: np.ndarray, after_lo: np.ndarray,
               after_hi: np.ndarray, fall: np.ndarray, n_err: int) -> Callable[[np.ndarray], np.ndarray]:
    """The least Error of one axis that leaves upwards at step k0 at rate v[k0], for every k0.

    Before step k0 the axis was in [lo, hi] (reachable inside the box) and rose at most
    `rise[l]` (rad/s) in step l, so sample i < k0 was ≥ v − Σ_{l=i+1…k0} rise[l]; after it,
    in [after_lo, after_hi], falling at most −fall[l] per step. Each sample costs at least
    its least distance to the command; inf where no such trajectory exists. For v above
    the command it grows with v.
    """
    K = len(lo)
    cum_rise = np.concatenate([[0.0], np.cumsum(rise)])
    cum_fall = np.concatenate([[0.0], np.cumsum(fall)])
    i, k0 = np.arange(K)[:, None], np.arange(K)[None, :]
    before, at = i < k0, i == k0
    climb = cum_rise[k0 + 1] - cum_rise[i + 1]  # Σ rise over steps i+1 … k0 (i < k0)
    drop = cum_fall[i + 1] - cum_fall[k0 + 1]  # Σ fall over steps k0+1 … i (i > k0)
    floor = np.where(before, lo[:, None], after_lo[:, None])
    ceiling = np.where(before, hi[:, None], after_hi[:, None])
    shift = np.where(before, -climb, drop)
    counted = (i < n_err) & ~at
    exit_counted = np.arange(K) < n_err

    def cost(v: np.ndarray) -> np.ndarray:
        low = np.maximum(floor, v[None, :] + shift)
        impossible = ((low > ceiling + 1e-12) & ~at).any(axis=0) | (v > cum_rise[1:] + 1e-12)  # from rest
        err = (_dist(command, low, ceiling) * counted).sum(axis=0)
        err += np.where(exit_counted, np.abs(v - command), 0.0)
        return np.where(impossible, np.inf, err + 2.0 * abs(command))

    return cost


def _exit_thresholds(command: float, budget: float, lo: np.ndarray, hi: np.ndarray, rise: np.ndarray,
                     after_lo: np.ndarray, after_hi: np.ndarray, fall: np.ndarray,
                     n_err: int) -> tuple[np.ndarray, np.ndarray]:
    """Per step k0, a rate v* past which a first exit upwards at k0 costs the axis > budget.

    Bisection on `exit_error` from the command up to just past `hi`. Where a rate just past
    `hi` would still cost ≤ budget, v* is `hi` and that step is flagged open (the second array).
    """
    cost = exit_error(command, lo, hi, rise, after_lo, after_hi, fall, n_err)
    K = len(lo)
    top = np.minimum(hi, HUGE)
    past = top + EDGE
    open_top = cost(past) <= budget
    a, b = np.minimum(np.full(K, command), top), past
    for _ in range(BISECTIONS):
        m = 0.5 * (a + b)
        under = cost(m) <= budget
        a, b = np.where(under, m, a), np.where(under, b, m)
    return np.where(open_top, hi, b), open_top
