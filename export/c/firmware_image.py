"""The bare-metal Cortex-M4F image around the exported policy, for QEMU's `mps2-an386`.

Startup (vector table, FPU enable, .data/.bss set-up), ARM semihosting for output and
exit, and a harness `main` that prints the target's outputs for the bench vectors as
float32 bit patterns, runs the policy's own self-test, measures the stack the policy
uses (painted words) and times `fcemu_policy_infer` with the CMSDK APB timer. Under
`-icount shift=0` QEMU advances virtual time by one tick of its instruction counter per
instruction, so timer ticks are proportional to instructions; a calibration loop of
exactly two instructions per iteration gives the ratio, so no clock rate is assumed.

A second image, the size probe, holds only startup and one `fcemu_policy_step` call:
`arm-none-eabi-size` on it is the policy's flash and static RAM. A third, the trace image,
calls `fcemu_policy_infer` on the first bench vectors and exits: `export.c.trace` follows it
instruction by instruction.
"""

from __future__ import annotations

ARM_FLAGS = ("-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard",
             "-std=c99", "-O2", "-funroll-loops", "-ffp-contract=off",
             "-ffunction-sections", "-fdata-sections")
STACK_BYTES = 0x40000
CALIBRATION_ITERATIONS = 1_000_000
TRACED_INFERENCES = 3

LINKER_SCRIPT = f"""\
MEMORY {{
  FLASH (rx) : ORIGIN = 0x00000000, LENGTH = 4M
  RAM (rwx)  : ORIGIN = 0x20000000, LENGTH = 4M
}}
ENTRY(Reset_Handler)
_stack_top = ORIGIN(RAM) + LENGTH(RAM);
_stack_limit = _stack_top - {STACK_BYTES:#x};
SECTIONS {{
  .text : {{ KEEP(*(.vectors)) *(.text*) *(.rodata*) . = ALIGN(4); }} > FLASH
  .ARM.exidx : {{ *(.ARM.exidx*) }} > FLASH
  _sidata = LOADADDR(.data);
  .data : {{ _sdata = .; *(.data*) . = ALIGN(4); _edata = .; }} > RAM AT > FLASH
  .bss (NOLOAD) : {{ _sbss = .; *(.bss*) *(COMMON) . = ALIGN(4); _ebss = .; }} > RAM
}}
"""

STARTUP = """\
#include <stdint.h>

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _stack_top;
int main(void);

int semihost(int op, const void *arg) {
    register int r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void semihost_exit(int ok) {
    semihost(0x18, (const void *)(ok ? 0x20026u : 0x20023u));  /* SYS_EXIT: application exit / error */
    for (;;) {}
}

void Fault_Handler(void) {
    semihost(0x04, "FAULT\\n");
    semihost_exit(0);
}

void Reset_Handler(void) {
    *(volatile uint32_t *)0xE000ED88 |= 0xFu << 20;  /* CPACR: full access to CP10/CP11 (the FPU) */
    __asm__ volatile("dsb\\n isb");
    for (uint32_t *src = &_sidata, *dst = &_sdata; dst < &_edata;) *dst++ = *src++;
    for (uint32_t *dst = &_sbss; dst < &_ebss;) *dst++ = 0;
    semihost_exit(main() == 0);
}

__attribute__((section(".vectors"), used)) void (*const vectors[16])(void) = {
    (void (*)(void))&_stack_top, Reset_Handler, Fault_Handler, Fault_Handler, Fault_Handler,
    Fault_Handler, Fault_Handler, 0, 0, 0, 0, Fault_Handler, Fault_Handler, 0, Fault_Handler, Fault_Handler,
};
"""

SIZE_PROBE = """\
#include "fcemu_policy.h"

static fcemu_policy_state state;
static volatile float inputs[3 + 3 + 4 + 1];
volatile float pwm_out[4];

int main(void) {
    float sp[3], gyro[3], rotor[4], pwm[4] = {0};
    for (int i = 0; i < 3; ++i) { sp[i] = inputs[i]; gyro[i] = inputs[3 + i]; }
    for (int i = 0; i < 4; ++i) rotor[i] = inputs[6 + i];
    fcemu_policy_reset(&state);
    int status = fcemu_policy_step(&state, sp, gyro, rotor, inputs[10], pwm);
    for (int i = 0; i < 4; ++i) pwm_out[i] = pwm[i];
    return status;
}
"""

TRACE_HARNESS = f"""\
#include "fcemu_policy.h"

extern const int bench_count;
extern const float bench_obs[][FCEMU_OBS_SIZE];
volatile float sink;

int main(void) {{
    float action[FCEMU_ACTION_SIZE];
    for (int n = 0; n < {TRACED_INFERENCES}; ++n) {{
        fcemu_policy_infer(bench_obs[n % bench_count], action);
        sink = action[0];
    }}
    return 0;
}}
"""

HARNESS = f"""\
#include <stdint.h>
#include "fcemu_policy.h"

#define TIMER_CTRL (*(volatile uint32_t *)0x40000000)
#define TIMER_VALUE (*(volatile uint32_t *)0x40000004)
#define TIMER_RELOAD (*(volatile uint32_t *)0x40000008)
#define PAINT 0xA5C3E1F7u

int semihost(int op, const void *arg);
extern uint32_t _stack_limit;
extern const int bench_count;
extern const float bench_obs[][FCEMU_OBS_SIZE];
volatile float sink;

static void put(const char *s) {{ semihost(0x04, s); }}

static void put_u32(uint32_t v, int hex) {{
    char buf[12];
    int n = 11;
    buf[n] = 0;
    do {{
        uint32_t d = hex ? v % 16 : v % 10;
        buf[--n] = (char)(d < 10 ? '0' + d : 'a' + d - 10);
        v = hex ? v / 16 : v / 10;
    }} while (v);
    put(&buf[n]);
    put(" ");
}}

static uint32_t bits(float f) {{
    union {{ float f; uint32_t u; }} x = {{f}};
    return x.u;
}}

__attribute__((noinline)) static void paint_stack(uint32_t *top) {{
    for (uint32_t *p = &_stack_limit; p < top; ++p) *p = PAINT;
}}

__attribute__((noinline)) static void calibrate(uint32_t n) {{
    __asm__ volatile("1: subs %0, %0, #1\\n bne 1b" : "+r"(n) :: "cc");
}}

static uint32_t now(void) {{ return TIMER_VALUE; }}

int main(void) {{
    float action[FCEMU_ACTION_SIZE];
    for (int n = 0; n < bench_count; ++n) {{
        fcemu_policy_infer(bench_obs[n], action);
        put("G ");
        put_u32((uint32_t)n, 0);
        for (int i = 0; i < FCEMU_ACTION_SIZE; ++i) put_u32(bits(action[i]), 1);
        put("\\n");
    }}

    float worst = 0.0f;
    int failures = fcemu_self_test(FCEMU_SELF_TEST_TOLERANCE, &worst);
    put("SELFTEST ");
    put_u32((uint32_t)failures, 0);
    put_u32(bits(worst), 1);
    put("\\n");

    uint32_t marker;
    uint32_t *top = &marker - 64;  /* below main's frame and paint_stack's own */
    paint_stack(top);
    fcemu_policy_state state;
    float sp[3] = {{0.1f, -0.2f, 0.3f}}, gyro[3] = {{0}}, rotor[4] = {{500, 500, 500, 500}}, pwm[4];
    fcemu_policy_reset(&state);
    fcemu_policy_step(&state, sp, gyro, rotor, 0.5f, pwm);
    uint32_t *p = &_stack_limit;
    while (p < top && *p == PAINT) ++p;
    put("STACK ");
    put_u32((uint32_t)((top - p) * 4), 0);
    put("\\n");

    TIMER_RELOAD = 0xFFFFFFFFu;
    TIMER_VALUE = 0xFFFFFFFFu;
    TIMER_CTRL = 1u;
    uint32_t t0 = now();
    calibrate({CALIBRATION_ITERATIONS}u);
    uint32_t t1 = now();
    for (int n = 0; n < FCEMU_TIMED_INFERENCES; ++n) {{
        fcemu_policy_infer(bench_obs[n % bench_count], action);
        sink = action[0];
    }}
    uint32_t t2 = now();
    for (int n = 0; n < FCEMU_TIMED_INFERENCES; ++n) {{
        sink = bench_obs[n % bench_count][0];
    }}
    uint32_t t3 = now();
    put("CAL ");
    put_u32(t0 - t1, 0);
    put_u32({CALIBRATION_ITERATIONS}u * 2u, 0);
    put("\\nTIME ");
    put_u32(t1 - t2, 0);
    put_u32(t2 - t3, 0);
    put_u32(FCEMU_TIMED_INFERENCES, 0);
    put("\\nDONE\\n");
    return failures != 0;
}}
"""
