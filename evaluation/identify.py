"""What a rate controller depends on, fitted to a flight log by least squares.

The model is the twin's (`sim_bridge.plant`): each motor's speed follows its command
u (0..1) after `esc_delay` ticks through a first-order lag, ω ← ω + α(a + b·u − ω), α from
τ_up rising and τ_down falling; each axis accelerates by c·Σ(lever_i·ω_i²) (the lever: −y_i
on roll, x_i on pitch, the spin on yaw, from the base airframe's geometry), minus a damping
d·rate, plus the body's gyroscopic coupling g·Ω_a·Ω_b (roll q·r, pitch p·r, yaw p·q: the
inertia's ratios, g_roll = (I_yy − I_zz)/I_xx, which the identification flight's yawing doublets
excite) and on yaw the rotors' spin-up reaction j·Σ spin_i·dω_i/dt; the gyro reads the rate
`gyro_delay` ticks late. With ESC rpm in the log the motors are fitted to it and the rates to
the measured speeds; without, the rate fit takes the speeds its own motor model makes of the
commands and the time constants are those that fit the rates best (the base's up/down ratio).
Every estimate carries its 95 % interval (parameter covariance of the fit, residual variance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter, sosfiltfilt

from fcemu.evaluation.identify_log import IDLE, FlightLog
from fcemu.evaluation.rate_boxes import GYRO_PAIRS, gyro_coefficients
from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.sim_bridge.airframe import Airframe

MAX_DELAY_TICKS = 6
# A real quad's command-to-gyro delay (ESC, motor start, filters) reaches 10-15 ms: searched that far
# in time, and at least MAX_DELAY_TICKS samples.
MAX_DELAY_S = 0.015


def max_delay(dt: float) -> int:
    return max(MAX_DELAY_TICKS, round(MAX_DELAY_S / dt))
# The motor spin-up time constants a quad's motors have, from a 65 mm whoop's (~10 ms) to a large
# quad's (~150 ms): the rate response is searched inside, and a best at either end is not known.
TAU_UP_RANGE_S = (0.005, 0.2)
SMOOTH_HZ = 40.0
# Below this the air turns a flying quad as much as its motors do (forward flight's pitch-up, prop
# wash, a trim drifting with throttle): the motors' effectiveness is read above it.
BAND_LOW_HZ = 5.0
Z95 = 1.959964
AXES = ("roll", "pitch", "yaw")


@dataclass(frozen=True)
class Estimate:
    value: float
    low: float
    high: float

    @classmethod
    def normal(cls, value: float, std: float) -> Estimate:
        return cls(float(value), float(value - Z95 * std), float(value + Z95 * std))

    def text(self, unit: str = "") -> str:
        """The value and its interval, with digits enough to tell the three apart."""
        half = (self.high - self.low) / 2
        ratio = abs(self.value) / half if half > 0 else 1.0
        digits = int(np.clip(np.ceil(np.log10(max(ratio, 1.0))) + 2, 3, 9)) if half > 0 else 4
        return (f"{self.value:.{digits}g}{unit} (95 % interval {self.low:.{digits}g} to "
                f"{self.high:.{digits}g}{unit})")


@dataclass(frozen=True)
class MotorFit:
    delay_ticks: int
    speed_at_zero: Estimate  # a: rad/s the command 0 asks for (the line's intercept)
    speed_per_command: Estimate  # b: rad/s per unit of command
    tau_up: Estimate  # s
    tau_down: Estimate  # s
    from_rpm: bool  # fitted to the ESC rpm (else to the rates)
    at_edge: bool = False  # the rates' best time constant is at an end of the physical range: not known


@dataclass(frozen=True)
class AxisFit:
    effectiveness: Estimate  # c: rad/s² per (rad/s)² of lever-weighted rotor speed squared
    damping: Estimate  # d: 1/s
    spin_up: Estimate | None  # j (yaw only): rad/s² per rad/s² of signed rotor acceleration
    coupling: Estimate  # g: rad/s² per (rad/s)² of the other two rates' product
    delay_ticks: int
    rms: float  # rad/s² of the acceleration residual
    bias: Estimate = Estimate(0.0, 0.0, 0.0)  # rad/s² with the rates still: a trim the thrust makes


@dataclass(frozen=True)
class RateFit:
    axes: tuple[AxisFit, AxisFit, AxisFit]
    gyro_delay_ticks: int
    accel: np.ndarray  # (T, 3) modelled acceleration at each tick (the last row repeated), rad/s²
    speed: np.ndarray  # (T, 4) rotor speed the fit used, rad/s


def levers(airframe: Airframe) -> np.ndarray:
    """(3, 4): each rotor's share in roll, pitch and yaw torque per unit thrust (yaw per k_M)."""
    p = airframe.rotor_positions
    return np.stack([-p[:, 1], p[:, 0], airframe.yaw_sign])


def _tau(alpha: float, dt: float) -> float:
    alpha = min(max(alpha, 1e-9), 1 - 1e-12)
    return -dt / np.log1p(-alpha)


def _tau_estimate(alpha: float, std: float, dt: float) -> Estimate:
    """τ from α; its interval is α's mapped through the (decreasing) τ(α)."""
    return Estimate(_tau(alpha, dt), _tau(alpha + Z95 * std, dt), _tau(alpha - Z95 * std, dt))


def _covariance(jac: np.ndarray, residual: np.ndarray) -> np.ndarray:
    n, p = jac.shape
    sigma2 = float(residual @ residual) / max(n - p, 1)
    return np.linalg.pinv(jac.T @ jac) * sigma2


def fit_motors(log: FlightLog) -> MotorFit:
    """The motor lag, delay and speed line fitted to the ESC rpm (the log must have it)."""
    assert log.rotor_speed is not None
    w, u, dt = log.rotor_speed, log.command, log.dt
    best = None
    for delay in range(MAX_DELAY_TICKS + 1):
        n = len(w) - 1 - delay
        if n < 50:
            break
        step = (w[delay + 1:] - w[delay:-1]).ravel()
        speed = w[delay:-1].ravel()
        cmd = u[:n].ravel()
        ok = (cmd > IDLE) & (cmd < 0.99)
        step, speed, cmd = step[ok], speed[ok], cmd[ok]
        # A symmetric lag first, linear in (α·a, α·b, α); then up and down apart.
        x = np.stack([np.ones_like(cmd), cmd, -speed], axis=1)
        p0, p1, alpha = np.linalg.lstsq(x, step, rcond=None)[0]
        alpha = float(np.clip(alpha, 1e-4, 0.9))

        def residual(theta: np.ndarray, step=step, speed=speed, cmd=cmd) -> np.ndarray:
            a, b, up, down = theta
            gap = a + b * cmd - speed
            return step - np.where(gap > 0, up, down) * gap

        fit = least_squares(residual, [p0 / alpha, p1 / alpha, alpha, alpha], method="lm")
        if best is None or fit.cost < best[1].cost:
            best = (delay, fit)
    if best is None:
        raise ValueError("too few ESC rpm samples to fit the motors")
    delay, fit = best
    std = np.sqrt(np.diag(_covariance(fit.jac, fit.fun)))
    a, b, up, down = fit.x
    return MotorFit(delay, Estimate.normal(a, std[0]), Estimate.normal(b, std[1]),
                    _tau_estimate(up, std[2], dt), _tau_estimate(down, std[3], dt), from_rpm=True)


def lagged_speed(target: np.ndarray, alpha_up: np.ndarray, alpha_down: np.ndarray,
                 start: np.ndarray) -> np.ndarray:
    """(G, T, 4): the lag ω ← ω + α(target − ω) of `target` (T, 4) for G pairs of (α_up, α_down)."""
    out = np.empty((len(alpha_up), *target.shape))
    w = np.broadcast_to(start, (len(alpha_up), 4)).copy()
    up, down = alpha_up[:, None], alpha_down[:, None]
    for k in range(len(target)):
        out[:, k] = w
        gap = target[k] - w
        w += np.where(gap > 0, up, down) * gap
    return out


def axis_regressors(speed: np.ndarray, lever: np.ndarray, dt: float, axis: int) -> np.ndarray:
    """(T, n) columns per tick k: lever-weighted ω² at k+1 and, on yaw, the signed spin-up."""
    torque = (speed**2) @ lever[axis]
    columns = [np.append(torque[1:], torque[-1])]
    if axis == 2:
        spin = speed @ lever[2]
        columns.append(np.append(np.diff(spin) / dt, 0.0))
    return np.stack(columns, axis=1)


def coupling_regressor(rates: np.ndarray, axis: int) -> np.ndarray:
    """(T,) the product of the other two rates that the body's gyroscopic term on `axis` scales."""
    a, b = GYRO_PAIRS[axis]
    return rates[:, a] * rates[:, b]


def smooth(x: np.ndarray, dt: float) -> np.ndarray:
    """The same zero-phase low-pass on both sides of the fit: the relation between rate and rotor
    speeds is linear, so it holds of the filtered signals, which lose the gyro's noise and the
    rotors' vibration (above `SMOOTH_HZ`)."""
    sos = butter(4, SMOOTH_HZ, fs=1.0 / dt, output="sos")
    return sosfiltfilt(sos, x, axis=0)


def band(x: np.ndarray, dt: float) -> np.ndarray:
    """`smooth` less what is slower than `BAND_LOW_HZ`: where the motors, not the air, turn the body."""
    sos = butter(2, BAND_LOW_HZ, fs=1.0 / dt, output="sos")
    return smooth(x, dt) - sosfiltfilt(sos, x, axis=0)


def _design(columns: np.ndarray, rates: np.ndarray, axis: int, delay: int, n: int) -> np.ndarray:
    return np.column_stack([columns[:n], -rates[delay:delay + n, axis],
                            coupling_regressor(rates[delay:delay + n], axis)])


def fit_rates(log: FlightLog, speed: np.ndarray, lever: np.ndarray) -> RateFit:
    """Per axis c, d, g (and j on yaw) by least squares in the motors' band (`band`), at the gyro
    delay that fits best; then the steady acceleration they leave over the whole band (a trim)."""
    dt = log.dt
    g = smooth(log.gyro, dt)
    accel = np.diff(g, axis=0) / dt  # tick k → k + 1
    g_band = band(log.gyro, dt)
    products = band(np.stack([coupling_regressor(log.gyro, a) for a in range(3)], axis=1), dt)
    accel_band = np.diff(g_band, axis=0) / dt
    fits: list[AxisFit] = []
    results = []
    for axis in range(3):
        columns = smooth(axis_regressors(speed, lever, dt, axis), dt)
        columns_band = band(axis_regressors(speed, lever, dt, axis), dt)
        best = None
        for delay in range(max_delay(dt) + 1):
            n = len(accel) - delay
            x = np.column_stack([columns_band[:n], -g_band[delay:delay + n, axis],
                                 products[delay:delay + n, axis]])
            y = accel_band[delay:, axis]
            beta, *_ = np.linalg.lstsq(x, y, rcond=None)
            residual = y - x @ beta
            if best is None or residual @ residual < best[0]:
                best = (float(residual @ residual), delay, x, beta, residual)
        _, delay, x, beta, residual = best
        # The filtered residual is correlated over about 1 / (2·SMOOTH_HZ·dt) ticks: count them as one sample.
        std = np.sqrt(np.diag(_covariance(x, residual) / (2 * SMOOTH_HZ * dt)))
        n = len(accel) - delay
        whole = _design(columns, g, axis, delay, n) @ beta
        left = accel[delay:, axis] - whole
        bias = Estimate.normal(float(left.mean()), float(left.std() * np.sqrt(2 * SMOOTH_HZ * dt / n)))
        spin = Estimate.normal(beta[1], std[1]) if axis == 2 else None
        k = 2 if axis == 2 else 1
        coupling = Estimate.normal(beta[k + 1], std[k + 1])
        fits.append(AxisFit(Estimate.normal(beta[0], std[0]), Estimate.normal(beta[k], std[k]), spin,
                            coupling, delay, float(np.sqrt(np.mean(residual**2))), bias))
        results.append((delay, columns_band, beta))
    gyro_delay = int(np.median([f.delay_ticks for f in fits]))
    modelled = np.zeros((len(g), 3))
    for axis, (delay, columns_band, beta) in enumerate(results):
        n = len(g) - delay
        modelled[delay:, axis] = np.column_stack([columns_band[:n], -g_band[delay:, axis],
                                                  products[delay:, axis]]) @ beta
    return RateFit((fits[0], fits[1], fits[2]), gyro_delay, modelled, speed)


def fit_without_rpm(log: FlightLog, base: Airframe, lever: np.ndarray) -> tuple[MotorFit, RateFit]:
    """No ESC telemetry: the base's speed line; the time constants (the base's up/down ratio kept)
    and the command-to-gyro delay are those whose modelled speeds fit the rates best: a coarse
    search over scales of the base's time constants and the delays, then a fine one around the best."""
    m = base.motor
    pwm = PWM_MIN + PWM_SPAN * log.command
    target = np.clip(pwm, m.pwm_min, m.pwm_max) - m.pwm_min
    target *= m.max_rotor_speed / (m.pwm_max - m.pwm_min)
    dt = log.dt
    g = band(log.gyro, dt)
    accel = np.diff(g, axis=0) / dt

    def scores(scale: np.ndarray, delays: range) -> tuple[np.ndarray, np.ndarray]:
        up, down = 1 - np.exp(-dt / (m.tau_up * scale)), 1 - np.exp(-dt / (m.tau_down * scale))
        speeds = lagged_speed(target, up, down, target[0])
        out = np.zeros((len(scale), len(delays)))
        for i in range(len(scale)):
            for axis in range(3):
                columns = band(axis_regressors(speeds[i], lever, dt, axis), dt)
                for j, delay in enumerate(delays):
                    n = len(accel) - delay
                    x = np.column_stack([columns[:n], -g[delay:delay + n, axis]])
                    y = accel[delay:, axis]
                    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
                    out[i, j] += float(np.sum((y - x @ beta) ** 2))
        return out, speeds

    coarse = np.geomspace(TAU_UP_RANGE_S[0] / m.tau_up, TAU_UP_RANGE_S[1] / m.tau_up, 29)
    coarse_scores, _ = scores(coarse, range(max_delay(dt) + 1))
    i, delay = np.unravel_index(np.argmin(coarse_scores), coarse_scores.shape)
    step = coarse[1] / coarse[0]
    fine = np.clip(coarse[i] * np.geomspace(1 / step, step, 21), coarse[0], coarse[-1])
    fine_scores, speeds = scores(fine, range(delay, delay + 1))
    best = int(np.argmin(fine_scores[:, 0]))
    # The scale's interval: where the residual sum of squares stays within χ²(1)'s 95 % of its least,
    # counting the filtered ticks as 1 / (2·SMOOTH_HZ·dt) as many independent samples, and at
    # least the fine search's step either side.
    n_eff = 3 * len(accel) * 2 * SMOOTH_HZ * dt
    within = fine[fine_scores[:, 0] <= fine_scores[best, 0] * (1 + Z95**2 / n_eff)]
    fine_step = fine[1] / fine[0]
    lo, hi = min(within.min(), fine[best] / fine_step), max(within.max(), fine[best] * fine_step)
    rate = fit_rates(log, speeds[best], lever)
    b = m.max_rotor_speed * PWM_SPAN / (m.pwm_max - m.pwm_min)
    a = -b * (m.pwm_min - PWM_MIN) / PWM_SPAN
    motors = MotorFit(0, Estimate(a, a, a), Estimate(b, b, b),
                      Estimate(m.tau_up * fine[best], m.tau_up * lo, m.tau_up * hi),
                      Estimate(m.tau_down * fine[best], m.tau_down * lo, m.tau_down * hi), from_rpm=False,
                      at_edge=bool(np.isclose(fine[best], coarse[0]) or np.isclose(fine[best], coarse[-1])))
    return motors, rate


def hover_command(log: FlightLog, blocks: int = 20) -> Estimate:
    """The collective the flight holds: the median of the collective setpoint where the log has
    it (the mixer may move the motors' mean off it to keep the demands unclipped), else of the
    motors' mean command; its interval from the spread of the medians of `blocks` stretches."""
    collective = log.command.mean(axis=1) if log.throttle is None else log.throttle
    medians = np.array([np.median(part) for part in np.array_split(collective, blocks)])
    return Estimate.normal(float(np.median(collective)), float(medians.std(ddof=1) / np.sqrt(blocks)))


def predict_ahead(log: FlightLog, accel: np.ndarray, horizon: int) -> np.ndarray:
    """(T, 3) rates predicted `horizon` ticks ahead from the measured rate and the modelled
    acceleration in between (NaN for the first `horizon` ticks)."""
    area = np.vstack([np.zeros((1, 3)), np.cumsum(accel[:-1], axis=0) * log.dt])
    out = np.full_like(log.gyro, np.nan)
    out[horizon:] = log.gyro[:-horizon] + area[horizon:] - area[:-horizon]
    return out


def airframe_accel(log: FlightLog, speed: np.ndarray, airframe: Airframe, lever: np.ndarray) -> np.ndarray:
    """(T, 3) the acceleration `airframe`'s twin gives the logged rotor speeds and rates (its
    effectiveness, damping, gyroscopic coupling, spin-up reaction and gyro delay, the twin's own
    tick included), in the motors' band (`band`): slower, a flying quad's air and trim balance
    the motors, which no twin on a rig has."""
    inertia = airframe.inertia()
    m = airframe.motor
    c = [m.kf / inertia[0], m.kf / inertia[1], m.kf * m.km / inertia[2]]
    coupling = gyro_coefficients(inertia)
    damping = np.array(airframe.rate_damping) / inertia
    # the twin's gyro delay counts its 1 ms physics steps (and one of its own); a filtered gyro adds its lag
    delay = round(((airframe.gyro_delay_ticks + 1) * 0.001 + log.gyro_filter_lag_s) / log.dt)
    g = band(log.gyro, log.dt)
    products = band(np.stack([coupling_regressor(log.gyro, a) for a in range(3)], axis=1), log.dt)
    out = np.zeros_like(g)
    n = len(g) - delay
    for axis in range(3):
        columns = band(axis_regressors(speed, lever, log.dt, axis), log.dt)
        coef = [c[axis]] + ([airframe.rotor_inertia / inertia[2]] if axis == 2 else [])
        out[delay:, axis] = (columns[:n] @ np.array(coef) - damping[axis] * g[delay:, axis]
                             + coupling[axis] * products[delay:, axis])
    return out


def prediction_fit(log: FlightLog, predicted: np.ndarray) -> np.ndarray:
    """(3,) per axis, 100·(1 − ‖measured − predicted‖ / ‖measured − its mean‖) where predicted."""
    ok = np.isfinite(predicted).all(axis=1)
    y, p = log.gyro[ok], predicted[ok]
    return 100.0 * (1.0 - np.linalg.norm(y - p, axis=0) / np.linalg.norm(y - y.mean(axis=0), axis=0))
