"""The firmware side of a policy's contract, generated as C99 from its metadata.

`contract_sources` is the one place that turns the ONNX metadata (observation spec,
action mapping, loop rate) into C: constants, the observation builder (rate error,
rotor speeds, optional leaky integral and leaky RMS of the rate error and the previous
tick's motor outputs; `memory` steps, newest first) and the
action-to-PWM mapping. It mirrors `firmware.observation` and `firmware.action` in
float32 — what a Cortex-M4F computes in hardware — so the host parity tests compare
the two within float32 rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

from fcemu.firmware.action import ACTION_MAPPINGS, DIFFERENTIAL_GAIN, PWM_MIN, PWM_SPAN
from fcemu.firmware.mixer import BETAFLIGHT_QUAD_X
from fcemu.firmware.observation import AUTHORITY_EPSILON, FIELD_DEFS, ObservationSpec

NET_FUNCTION = "fcemu_net"
ACTION_SIZE = 4
SELF_TEST_TOLERANCE = 1e-4  # golden vectors: float32 network code against onnxruntime, any libm


@dataclass(frozen=True)
class Contract:
    spec: ObservationSpec
    action_mapping: str
    loop_rate_hz: float


def c_float(x: float) -> str:
    """A float32 literal that round-trips exactly."""
    import numpy as np

    return f"{float(np.float32(x)).hex()}f"


# C for each source signal and scale named in firmware.observation.FIELD_DEFS: the field
# table is the one definition; a new field there needs only these two maps to cover it.
_SOURCE_C = {"rate_error": "(setpoint[i] - gyro[i])", "rotor_speed": "rotor_speed[i]", "gyro": "gyro[i]",
             "motor_output": "(s->fresh ? clampf(rotor_speed[i] * FCEMU_ROTOR_SPEED_SCALE, 0.0f, 1.0f)"
                             " : s->motor_output[i])",
             "loop_delay": "s->loop_delay_ticks"}
_SCALE_C = {"rate_scale": "FCEMU_RATE_SCALE", "rotor_speed_scale": "FCEMU_ROTOR_SPEED_SCALE",
            "loop_delay_scale": "FCEMU_LOOP_DELAY_SCALE"}
# Per integrated field: its state member in `fcemu_policy_state` and its λ's constant.
_STATE_C = {"integral_leak": ("integral", "FCEMU_INTEGRAL_LEAK"),
            "rms_leak": ("mean_square", "FCEMU_RMS_LEAK")}


def _field_code(name: str, k: int, spec: ObservationSpec) -> str:
    field = FIELD_DEFS[name]
    value = _SOURCE_C[field.source] + ("" if field.scale is None else f" * {_SCALE_C[field.scale]}")
    if spec.per_airframe_rotor_speed:  # the flown airframe's, set at boot (`fcemu_policy_configure`)
        value = value.replace("FCEMU_ROTOR_SPEED_SCALE", "s->rotor_speed_scale")
    if not field.leak or field.slope:  # the slope's input: `_authority_code` turns it into the estimate
        return f"        step[{k} + i] = {value};"
    state, leak = _STATE_C[field.leak]
    update = "x * x" if field.rms else "x"
    out = f"sqrtf(s->{state}[i])" if field.rms else f"s->{state}[i]"
    return (f"        float x = {value};\n"
            f"        float carried = s->fresh ? 0.0f : {leak} * s->{state}[i];\n"
            f"        s->{state}[i] = carried + (1.0f - {leak}) * ({update});\n"
            f"        step[{k} + i] = {out};")


_ACTION_CODE = {
    "gymfc": """\
    for (int i = 0; i < 4; ++i) {
        pwm[i] = FCEMU_PWM_MIN + 0.5f * FCEMU_PWM_SPAN * (clampf(action[i], -1.0f, 1.0f) + 1.0f);
    }
    (void)throttle;""",
    "throttle": """\
    float a[4], mix[4];
    for (int i = 0; i < 4; ++i) a[i] = clampf(action[i], -1.0f, 1.0f);
    const float mean = (((a[0] + a[1]) + a[2]) + a[3]) * 0.25f;
    for (int i = 0; i < 4; ++i) mix[i] = FCEMU_DIFFERENTIAL_GAIN * (a[i] - mean);
    float lo = mix[0], hi = mix[0];
    for (int i = 1; i < 4; ++i) {
        if (mix[i] < lo) lo = mix[i];
        if (mix[i] > hi) hi = mix[i];
    }
    /* A mix wider than the output range is scaled to fit; airmode shifts the collective. */
    const float span = hi - lo;
    const float scale = 1.0f / (span > 1.0f ? span : 1.0f);
    float t = clampf(throttle, 0.0f, 1.0f);
    t = fminf(fmaxf(t, -lo * scale), 1.0f - hi * scale);
    for (int i = 0; i < 4; ++i) {
        pwm[i] = FCEMU_PWM_MIN + FCEMU_PWM_SPAN * clampf(t + mix[i] * scale, 0.0f, 1.0f);
    }""",
}


def _authority_code(spec: ObservationSpec) -> str:
    """`observation.AuthorityEstimate` in float32, in the same order of operations: after the step's
    fields (the authority columns hold the scaled gyro), before the history takes the step."""
    if spec.slope is None:
        return ""
    cols, rotor = spec.slope
    mix = ", ".join("{" + ", ".join(c_float(v) for v in row) + "}" for row in BETAFLIGHT_QUAD_X)
    terms = "; ".join(f"x = x + thrust[{i}] * mix[{i}][a]" for i in range(1, 4))
    return f"""
    {{  /* authority: the leaky least-squares slope of the gyro's change on the mixer's thrust differential */
        static const float mix[4][3] = {{{mix}}};
        const float keep = FCEMU_AUTHORITY_LEAK, take = 1.0f - FCEMU_AUTHORITY_LEAK;
        float thrust[4];
        for (int i = 0; i < 4; ++i) thrust[i] = step[{rotor.start} + i] * step[{rotor.start} + i];
        for (int a = 0; a < 3; ++a) {{
            float x = thrust[0] * mix[0][a]; {terms};
            const float g = step[{cols.start} + a];
            float *m = s->slope[a];  /* gyro, x, y, x·y, x² */
            if (s->fresh) {{
                m[0] = g; m[1] = x; m[2] = 0.0f; m[3] = 0.0f; m[4] = x * x;
            }} else {{
                const float y = g - m[0];
                m[0] = g;
                m[1] = keep * m[1] + take * x;
                m[2] = keep * m[2] + take * y;
                m[3] = keep * m[3] + take * (x * y);
                m[4] = keep * m[4] + take * (x * x);
            }}
            const float cov = m[3] - m[1] * m[2], var = m[4] - m[1] * m[1];
            step[{cols.start} + a] = FCEMU_AUTHORITY_SCALE * cov / (var + FCEMU_AUTHORITY_EPSILON);
        }}
    }}"""


def contract_sources(contract: Contract) -> dict[str, str]:
    """`fcemu_policy.h` and `fcemu_policy.c` for one policy's contract."""
    spec = contract.spec
    if contract.action_mapping not in ACTION_MAPPINGS:
        raise ValueError(f"action mapping {contract.action_mapping!r} unknown (known: {ACTION_MAPPINGS})")
    fields, k = [], 0
    for name in spec.fields:
        n = FIELD_DEFS[name].size
        loop = f"    for (int i = 0; i < {n}; ++i) {{  /* {name} */\n"
        fields.append(loop + _field_code(name, k, spec) + "\n    }")
        k += n
    constants = {
        "FCEMU_OBS_VERSION": str(spec.version),
        "FCEMU_OBS_MEMORY": str(spec.memory),
        "FCEMU_OBS_STEP_SIZE": str(spec.step_size),
        "FCEMU_OBS_SIZE": str(spec.size),
        "FCEMU_ACTION_SIZE": str(ACTION_SIZE),
        "FCEMU_RATE_SCALE": c_float(spec.rate_scale),
        "FCEMU_ROTOR_SPEED_SCALE": c_float(spec.rotor_speed_scale),
        "FCEMU_PER_AIRFRAME_ROTOR_SPEED": str(int(spec.per_airframe_rotor_speed)),
        "FCEMU_INTEGRAL_LEAK": c_float(spec.integral_leak),
        "FCEMU_RMS_LEAK": c_float(spec.rms_leak),
        "FCEMU_LOOP_DELAY_SCALE": c_float(spec.loop_delay_scale),
        "FCEMU_AUTHORITY_LEAK": c_float(spec.authority_leak),
        "FCEMU_AUTHORITY_SCALE": c_float(spec.authority_scale),
        "FCEMU_AUTHORITY_EPSILON": c_float(AUTHORITY_EPSILON),
        "FCEMU_DIFFERENTIAL_GAIN": c_float(DIFFERENTIAL_GAIN),
        "FCEMU_PWM_MIN": c_float(PWM_MIN),
        "FCEMU_PWM_SPAN": c_float(PWM_SPAN),
        "FCEMU_LOOP_RATE_HZ": c_float(contract.loop_rate_hz),
        "FCEMU_SELF_TEST_TOLERANCE": c_float(SELF_TEST_TOLERANCE),
    }
    defines = "\n".join(f"#define {name} {value}" for name, value in constants.items())
    header = f"""\
/* The policy's contract and entry points, generated by `fcemu export --target c`.
 * Observation fields, newest step first: {", ".join(spec.fields)} (memory {spec.memory}).
 * Action mapping: {contract.action_mapping}. No heap; float32; only math.h. */
#ifndef FCEMU_POLICY_H
#define FCEMU_POLICY_H

{defines}
#define FCEMU_ACTION_MAPPING "{contract.action_mapping}"

#define FCEMU_OK 0
#define FCEMU_NONFINITE_INPUT 1  /* the policy was not run; pwm is untouched */
#define FCEMU_NONFINITE_OUTPUT 2  /* pwm is untouched; fly the fallback controller this tick */

typedef struct {{
    float history[FCEMU_OBS_MEMORY][FCEMU_OBS_STEP_SIZE];
    float integral[3];
    float mean_square[3];
    float motor_output[4];  /* the last tick's PWM as 0..1, for a motor_output field */
    float loop_delay_ticks;  /* the configured ESC + gyro filter delay, for a loop_delay field */
    float rotor_speed_scale;  /* 1 / the flown top rotor speed, where the policy reads shares of it */
    float slope[3][5];  /* per axis, the authority estimate's last gyro and leaky means of x, y, x·y, x² */
    int fresh;
}} fcemu_policy_state;

/* At boot, from the configuration: the ESC protocol's and the gyro filters' delays, in ticks
 * (read by a loop_delay field), and the motors' top rotor speed in rad/s (read where the policy
 * observes rotor speeds as shares of it, FCEMU_PER_AIRFRAME_ROTOR_SPEED; 0: the trained airframe's).
 * Kept across resets. */
void fcemu_policy_configure(fcemu_policy_state *s, float loop_delay_ticks, float max_rotor_speed);
/* Start of flight (arming): the next observation fills the whole history. */
void fcemu_policy_reset(fcemu_policy_state *s);
/* sizeof(fcemu_policy_state), for callers that allocate the state outside C. */
int fcemu_policy_state_bytes(void);
/* Body rates rad/s (setpoint, gyro) and rotor speeds rad/s in; the network input out. */
void fcemu_observe(fcemu_policy_state *s, const float setpoint[3], const float gyro[3],
                   const float rotor_speed[4], float obs[FCEMU_OBS_SIZE]);
/* The network alone: observation in, raw action out. */
void fcemu_policy_infer(const float obs[FCEMU_OBS_SIZE], float action[FCEMU_ACTION_SIZE]);
/* Action in [-1, 1] (clipped here) and collective throttle 0..1 in; motor PWM (us) out. */
void fcemu_action_to_pwm(const float action[FCEMU_ACTION_SIZE], float throttle, float pwm[4]);
/* One control tick: observe, infer, map. Returns FCEMU_OK or a FCEMU_NONFINITE_* code. */
int fcemu_policy_step(fcemu_policy_state *s, const float setpoint[3], const float gyro[3],
                      const float rotor_speed[4], float throttle, float pwm[4]);

/* Golden vectors (observations and ONNX Runtime outputs) for an on-device self-test. */
extern const int fcemu_golden_count;
extern const float fcemu_golden_obs[][FCEMU_OBS_SIZE];
extern const float fcemu_golden_action[][FCEMU_ACTION_SIZE];
/* Runs the golden vectors; returns how many outputs differ by more than `tolerance`,
 * and the largest difference in *max_abs_diff. */
int fcemu_self_test(float tolerance, float *max_abs_diff);

#endif
"""
    source = f"""\
/* Generated by `fcemu export --target c` from the policy's metadata contract. */
#include <math.h>
#include "fcemu_policy.h"

void {NET_FUNCTION}(const float observation[1][FCEMU_OBS_SIZE], float action[1][FCEMU_ACTION_SIZE]);

static float clampf(float x, float lo, float hi) {{
    return x < lo ? lo : (x > hi ? hi : x);
}}

void fcemu_policy_configure(fcemu_policy_state *s, float loop_delay_ticks, float max_rotor_speed) {{
    s->loop_delay_ticks = loop_delay_ticks;
    s->rotor_speed_scale = max_rotor_speed > 0.0f ? 1.0f / max_rotor_speed : FCEMU_ROTOR_SPEED_SCALE;
}}

void fcemu_policy_reset(fcemu_policy_state *s) {{
    if (!(s->rotor_speed_scale > 0.0f)) s->rotor_speed_scale = FCEMU_ROTOR_SPEED_SCALE;  /* unconfigured */
    s->fresh = 1;
}}

int fcemu_policy_state_bytes(void) {{
    return (int)sizeof(fcemu_policy_state);
}}

void fcemu_observe(fcemu_policy_state *s, const float setpoint[3], const float gyro[3],
                   const float rotor_speed[4], float obs[FCEMU_OBS_SIZE]) {{
    float step[FCEMU_OBS_STEP_SIZE];
{chr(10).join(fields)}{_authority_code(spec)}
    if (s->fresh) {{
        for (int m = 0; m < FCEMU_OBS_MEMORY; ++m)
            for (int i = 0; i < FCEMU_OBS_STEP_SIZE; ++i) s->history[m][i] = step[i];
        s->fresh = 0;
    }} else {{
        for (int m = FCEMU_OBS_MEMORY - 1; m > 0; --m)
            for (int i = 0; i < FCEMU_OBS_STEP_SIZE; ++i) s->history[m][i] = s->history[m - 1][i];
        for (int i = 0; i < FCEMU_OBS_STEP_SIZE; ++i) s->history[0][i] = step[i];
    }}
    for (int m = 0; m < FCEMU_OBS_MEMORY; ++m)
        for (int i = 0; i < FCEMU_OBS_STEP_SIZE; ++i) obs[m * FCEMU_OBS_STEP_SIZE + i] = s->history[m][i];
}}

void fcemu_policy_infer(const float obs[FCEMU_OBS_SIZE], float action[FCEMU_ACTION_SIZE]) {{
    {NET_FUNCTION}((const float (*)[FCEMU_OBS_SIZE])obs, (float (*)[FCEMU_ACTION_SIZE])action);
}}

void fcemu_action_to_pwm(const float action[FCEMU_ACTION_SIZE], float throttle, float pwm[4]) {{
{_ACTION_CODE[contract.action_mapping]}
}}

int fcemu_policy_step(fcemu_policy_state *s, const float setpoint[3], const float gyro[3],
                      const float rotor_speed[4], float throttle, float pwm[4]) {{
    for (int i = 0; i < 3; ++i)
        if (!isfinite(setpoint[i]) || !isfinite(gyro[i])) return FCEMU_NONFINITE_INPUT;
    for (int i = 0; i < 4; ++i)
        if (!isfinite(rotor_speed[i])) return FCEMU_NONFINITE_INPUT;
    if (!isfinite(throttle)) return FCEMU_NONFINITE_INPUT;
    float obs[FCEMU_OBS_SIZE], action[FCEMU_ACTION_SIZE];
    fcemu_observe(s, setpoint, gyro, rotor_speed, obs);
    fcemu_policy_infer(obs, action);
    for (int i = 0; i < FCEMU_ACTION_SIZE; ++i)
        if (!isfinite(action[i])) return FCEMU_NONFINITE_OUTPUT;
    fcemu_action_to_pwm(action, throttle, pwm);
    for (int i = 0; i < 4; ++i) s->motor_output[i] = (pwm[i] - FCEMU_PWM_MIN) / FCEMU_PWM_SPAN;
    return FCEMU_OK;
}}

int fcemu_self_test(float tolerance, float *max_abs_diff) {{
    int failures = 0;
    float worst = 0.0f;
    for (int n = 0; n < fcemu_golden_count; ++n) {{
        float action[FCEMU_ACTION_SIZE];
        fcemu_policy_infer(fcemu_golden_obs[n], action);
        for (int i = 0; i < FCEMU_ACTION_SIZE; ++i) {{
            float d = fabsf(action[i] - fcemu_golden_action[n][i]);
            if (!(d <= tolerance)) ++failures;
            if (d > worst || d != d) worst = d;
        }}
    }}
    *max_abs_diff = worst;
    return failures;
}}
"""
    return {"fcemu_policy.h": header, "fcemu_policy.c": source}
