"""Quad X mixer: collective throttle plus roll/pitch/yaw demands to four PWM values.

Motor order is Betaflight's (1 rear-right, 2 front-right, 3 rear-left, 4 front-left) and
every table here takes FRD demands: positive roll raises the left motors, positive pitch
the front motors, positive yaw the counter-clockwise motors (2 and 3), whose larger drag
torque turns the nose right. The twin agrees (see `sim_bridge/twin.py`).

Saturation follows Betaflight's `mixTable` / `applyMixerAdjustment` (flight/mixer.c):
when the spread of the axis mix (max − min over motors, with 0 included) exceeds 1 — the
whole output range — the mix is scaled down by that range, so every axis keeps its
proportion instead of one motor clipping; then the throttle is moved into
[−min, 1 − max], so no motor clips at either end (airmode: the throttle is shifted up at
low stick as well as down at high stick). Without airmode Betaflight also fades the axis
authority to 50% as throttle goes to 0 (`airmodeTransitionPercent`).

The throttle is the collective as a fraction of the PWM span, PWM = 1000 + 1000·t with
zero demands, as for the neural controller's `throttle` action mapping (firmware/action.py),
so one setpoint means the same collective to both and hover is (hover_pwm − 1000) / 1000.
Armed outputs never go below the idle output (Betaflight's dshot_idle_value, or GymFC's
minthrottle 1070 µs = 7%); Betaflight's saturation arithmetic runs in its own output
space [idle, 2000] µs = [0, 1], into which the throttle is converted first.

The neural controller's `throttle` mapping (firmware/action.py) fits its differential the
same way in exact arithmetic, but not in floating point: Betaflight keeps 0 inside the
mix bounds (any table, not only zero-sum ones), clamps the throttle with a conditional
whose order differs from min(max()) when the scaled range rounds past 1, clips in µs after
the idle offset, and fades authority without airmode. Sharing one routine would move
the PID's or the policy's outputs by an ulp in those cases, so each keeps its own.
"""

from __future__ import annotations

from collections.abc import Sequence

MixTable = tuple[tuple[float, float, float], ...]

# Betaflight's mixerQuadX {throttle, roll, pitch, yaw} is written for its own axes: roll
# right-wing-down, pitch nose-DOWN (rear motors +1), and a yaw column that the mixer negates
# (`scaledAxisPidYaw = -scaledAxisPidYaw` unless yaw_motors_reversed), so that positive yaw
# raises motors 1 and 4 (CW props) and turns the nose left. In FRD: roll as is, pitch negated,
# yaw the stored column (Betaflight's sign flip and the FLU->FRD flip cancel).
#   Betaflight:  REAR_R {1, -1,  1, -1}  FRONT_R {1, -1, -1, 1}  REAR_L {1, 1, 1, 1}  FRONT_L {1, 1, -1, -1}
BETAFLIGHT_QUAD_X: MixTable = (
    (-1.0, -1.0, -1.0),  # 1 rear-right (CW)
    (-1.0, 1.0, 1.0),  # 2 front-right (CCW)
    (1.0, -1.0, 1.0),  # 3 rear-left (CCW)
    (1.0, 1.0, -1.0),  # 4 front-left (CW)
)

# The paper's Iris table (Koch et al. 2018; GymFC's Betaflight port, m_i = [roll, pitch, yaw]):
#   m1 = [-1.0, 0.598, -1.0]  m2 = [-0.927, -0.598, 1.0]  m3 = [1.0, 0.598, 1.0]  m4 = [0.927, -0.598, -1.0]
# GymFC fed it to the same Betaflight mix code (yaw negated) with Gazebo's FLU body rates, which
# are Betaflight's axes: rear motors +pitch (nose down), CW motors 1 and 4 up for +yaw (nose left).
# Mapped to FRD exactly as Betaflight's table: roll kept, pitch negated, yaw column kept. The other
# signs would make the paper's PID unstable on the twin; tests/firmware/test_mixer.py flies each axis.
PAPER_IRIS: MixTable = (
    (-1.0, -0.598, -1.0),  # 1 rear-right
    (-0.927, 0.598, 1.0),  # 2 front-right
    (1.0, -0.598, 1.0),  # 3 rear-left
    (0.927, 0.598, -1.0),  # 4 front-left
)

TABLES: dict[str, MixTable] = {"betaflight": BETAFLIGHT_QUAD_X, "paper_iris": PAPER_IRIS}


class QuadXMixer:
    """Throttle (0..1 of the PWM span) + FRD axis demands -> PWM µs in motor order, Betaflight saturation."""

    def __init__(
        self,
        table: str | Sequence[Sequence[float]] = "betaflight",
        idle: float = 0.055,
        airmode: bool = True,
        pwm_min: float = 1000.0,
        pwm_max: float = 2000.0,
        yaw_reversed: bool = False,
    ) -> None:
        if isinstance(table, str):
            if table not in TABLES:
                raise ValueError(f"unknown mixer table {table!r}; choose one of {sorted(TABLES)}")
            self.table_name = table
            rows = TABLES[table]
        else:
            self.table_name = "custom"
            rows = tuple(tuple(float(v) for v in row) for row in table)  # type: ignore[misc]
        if len(rows) != 4 or any(len(r) != 3 for r in rows):
            raise ValueError("a Quad X table has 4 rows of (roll, pitch, yaw)")
        # Betaflight's yaw_motors_reversed: props spinning "out", each motor the other way round
        self.yaw_reversed = bool(yaw_reversed)
        if self.yaw_reversed:
            rows = tuple((r, p, -y) for r, p, y in rows)
        if not 0.0 <= idle < 1.0:
            raise ValueError(f"idle must be in [0, 1), got {idle}")
        if pwm_max <= pwm_min:
            raise ValueError("pwm_max must exceed pwm_min")
        self.table: MixTable = rows
        self.idle = float(idle)
        self.airmode = bool(airmode)
        self.pwm_min, self.pwm_max = float(pwm_min), float(pwm_max)
        self.out_low = self.pwm_min + self.idle * (self.pwm_max - self.pwm_min)
        self.out_range = self.pwm_max - self.out_low
        self._span = self.pwm_max - self.pwm_min
        self._flat = [v for row in rows for v in row]
        self.mix_range = 0.0  # last unscaled motor-mix range; > 1 means the demands were scaled down
        self.throttle = 0.0  # last throttle in [idle, max] = [0, 1] after the airmode shift

    def throttle_for_pwm(self, pwm: float) -> float:
        """The throttle whose output with zero demands is `pwm` (e.g. the hover PWM)."""
        return (pwm - self.pwm_min) / (self.pwm_max - self.pwm_min)

    def reset(self) -> None:
        self.mix_range = 0.0
        self.throttle = 0.0

    def mix(self, demand: Sequence[float], throttle: float) -> list[float]:
        """Three demands (roll, pitch, yaw; 1.0 = the whole output range) -> four PWM µs."""
        r, p, y = demand
        a0, a1, a2, b0, b1, b2, c0, c1, c2, d0, d1, d2 = self._flat
        m = [r * a0 + p * a1 + y * a2, r * b0 + p * b1 + y * b2,
             r * c0 + p * c1 + y * c2, r * d0 + p * d1 + y * d2]
        hi = max(m[0], m[1], m[2], m[3], 0.0)
        lo = min(m[0], m[1], m[2], m[3], 0.0)
        spread = hi - lo
        self.mix_range = spread

        t = (self.pwm_min + self._span * throttle - self.out_low) / self.out_range  # to [idle, max] = [0, 1]
        t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t
        scale = 1.0
        if not self.airmode and t < 0.5:
            scale = 0.5 + t
        if spread > 1.0:
            scale /= spread
        lo *= scale
        hi *= scale
        t = -lo if t < -lo else 1.0 - hi if t > 1.0 - hi else t
        self.throttle = t

        low, span, top = self.out_low, self.out_range, self.pwm_max
        out = [0.0, 0.0, 0.0, 0.0]
        for i in range(4):
            v = low + span * (m[i] * scale + t)
            out[i] = low if v < low else top if v > top else v
        return out
