"""The paper's rate-control tasks: setpoint generators, the throttle draw and the reward.

Everything random takes a seed or a `numpy.random.Generator`, so the environments (which
draw from `np_random`) and the evaluator (which draws from a seed) share one definition.

- Episodic task (Koch et al. 2018): Ω* ~ U[-Ω_max, Ω_max]³, held for the whole episode.
- Inflight task (evaluation only): the episodic commands, each a step from steady hover:
  the rotors already at the speed the hover throttle commands, rates zero, level, and the
  controller warmed up by `INFLIGHT_WARMUP_S` of zero-rate flight before the step. The
  episodic task starts from rest, where much of every controller's Error is spin-up.
- Continuous task: pulses of random width and amplitude. We follow the paper's appendix
  (and GymFC's continuous environment): the setpoint rests at zero for U[0.1, 1] s, then
  a command Ω* ~ U[-Ω_max, Ω_max]³ is held for U[0.1, 1] s, then it returns to zero, and
  so on. Returning to zero keeps the recovery to level rate in the task, which is what a
  pilot letting go of the sticks asks for. `rest_s=None` gives back-to-back commands.
"""

from __future__ import annotations

import numpy as np

TRAINING_TASKS = ("episodic", "continuous")  # what the environments fly
EVAL_TASKS = (*TRAINING_TASKS, "inflight")  # what `fcemu eval --task` flies
INFLIGHT_WARMUP_S = 0.2  # s of zero-rate flight at hover before an inflight step

OMEGA_MAX = 5.24  # rad/s, the paper's command bound
HOLD_S = (0.1, 1.0)  # s, how long a continuous-task command is held
REST_S = (0.1, 1.0)  # s, how long the setpoint rests at zero between commands

Seed = int | np.random.Generator | None


def as_generator(seed: Seed) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def episodic_setpoint(rng: np.random.Generator, omega_max: float = OMEGA_MAX,
                      batch_shape: tuple[int, ...] = ()) -> np.ndarray:
    """One episode's command per batch element, (*batch_shape, 3) rad/s FRD."""
    return rng.uniform(-omega_max, omega_max, (*batch_shape, 3))


def pulse_schedule(rng: np.random.Generator, n_steps: int, dt: float = 0.001,
                   omega_max: float = OMEGA_MAX, hold_s: tuple[float, float] = HOLD_S,
                   rest_s: tuple[float, float] | None = REST_S) -> np.ndarray:
    """A continuous-task setpoint for `n_steps` samples, (n_steps, 3) rad/s FRD.

    Durations are drawn in seconds and rounded to whole steps (at least one); the draw
    order per pulse is rest width, command amplitude, hold width.
    """
    out = np.zeros((n_steps, 3))
    k = 0
    while k < n_steps:
        if rest_s is not None:
            k += max(1, round(rng.uniform(*rest_s) / dt))
        command = rng.uniform(-omega_max, omega_max, 3)
        width = max(1, round(rng.uniform(*hold_s) / dt))
        out[k:k + width] = command
        k += width
    return out


def draw_throttle(rng: np.random.Generator, throttle: float | tuple[float, float]) -> float:
    """The collective for the `throttle` action mapping: fixed, or U[lo, hi] per episode."""
    if isinstance(throttle, tuple | list):
        lo, hi = throttle
        return float(rng.uniform(lo, hi))
    return float(throttle)


def rate_reward(setpoint: np.ndarray, rate: np.ndarray, omega_max: float = OMEGA_MAX) -> np.ndarray:
    """The paper's reward −clip(Σ|Ω* − Ω| / (3·Ω_max), 0, 1), over any leading batch shape.

    The three axes are summed explicitly so a single vehicle and a batch add in the same
    order and give bit-identical rewards.
    """
    e = np.abs(setpoint - rate)
    return -np.minimum(np.maximum((e[..., 0] + e[..., 1] + e[..., 2]) / (3.0 * omega_max), 0.0), 1.0)


# The evaluator's commands: two controllers evaluated with the same seed see the same ones.

def episodic_commands(seed: Seed, n: int, omega_max: float = OMEGA_MAX) -> np.ndarray:
    """`n` episodic commands, (n, 3) rad/s FRD.

    The same values, in order, as `RateControlEnv(task="episodic")` reset once with
    `seed` and then without one, when the env draws nothing else (no randomisation,
    noise or throttle range).
    """
    return episodic_setpoint(as_generator(seed), omega_max, (n,))


def continuous_schedule(seed: Seed, duration_s: float, dt: float = 0.001,
                        omega_max: float = OMEGA_MAX, hold_s: tuple[float, float] = HOLD_S,
                        rest_s: tuple[float, float] | None = REST_S) -> np.ndarray:
    """A continuous-task setpoint trace of `duration_s` at `dt`, (round(duration_s/dt), 3)."""
    return pulse_schedule(as_generator(seed), round(duration_s / dt), dt, omega_max, hold_s, rest_s)
