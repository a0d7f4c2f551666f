"""The Cortex-M4 cycle count: the TRM tables on known histograms and streams, and a hand-written
loop of known cycle count traced in QEMU."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from fcemu.export.c import firmware_image as image
from fcemu.export.c.cycles import Instruction, decode, flash_waits, histogram_cycles, weigh
from fcemu.export.c.trace import traced_calls
from tests.export.mcu_tools import require_target_tools

pytestmark = pytest.mark.no_wall_clock

ITERATIONS = 100
REFILL = 2
KNOWN_LOOP = """\
    .syntax unified
    .thumb
    .text
    .global known_loop
    .type known_loop, %function
    .balign 16
known_loop:                     @ r0 = iterations, r1 = three words
1:  vldr     s0, [r1]           @ 2
    vmla.f32 s1, s2, s3         @ 3, + 1: the next instruction reads s1
    vadd.f32 s4, s1, s5         @ 1
    ldr      r2, [r1, #4]       @ 2
    ldr      r3, [r1, #8]       @ 1: pipelined behind the load before it
    adds     r2, r2, r3         @ 1
    subs     r0, r0, #1         @ 1
    bne      1b                 @ 1 + P taken, 1 not taken
    bx       lr                 @ 1 + P
    .size known_loop, . - known_loop
"""
IT_LOOP = """\
    .syntax unified
    .thumb
    .text
    .global known_loop
    .type known_loop, %function
known_loop:                     @ r0 = iterations
1:  cmp      r0, #50            @ 1
    ite      lt                 @ 0: folded onto the 16-bit cmp
    addlt    r2, r2, #1         @ 1 (the TRM's 1 also when the condition fails)
    addge    r3, r3, #1         @ 1
    subs     r0, r0, #1         @ 1
    bne      1b                 @ 1 + P taken, 1 not taken
    bx       lr                 @ 1 + P
    .size known_loop, . - known_loop
"""
KNOWN_MAIN = """\
void known_loop(unsigned n, const float *words);
static const float words[3] = {1.0f, 2.0f, 3.0f};
int main(void) {
    known_loop(%d, words);
    return 0;
}
"""


def _stream(*rows: tuple[str, str, int]) -> list[tuple[Instruction, int]]:
    """Straight-line instructions at consecutive addresses (mnemonic, operands, size)."""
    out, address = [], 0x100
    for mnemonic, operands, size in rows:
        out.append((Instruction(address, size, mnemonic, operands), address + size))
        address += size
    return out


def test_decode_strips_width_condition_and_flags() -> None:
    assert decode("bne.n") == decode("beq")
    assert decode("bne.n").base == "b" and decode("bne.n").conditional
    assert [decode(m).base for m in ("adds.w", "addseq", "lsls", "bics", "movs", "vmul.f32", "vcvt.s32.f32",
                                     "itte", "vmls.f32", "bl", "blt")] == \
        ["add", "add", "lsl", "bic", "mov", "vmul", "vcvt", "it", "vmls", "bl", "b"]


def test_histogram_weighs_each_key_at_its_table_cost() -> None:
    counts = {"vldr": 10, "vmul": 10, "vadd": 10, "vmla": 1, "vdiv": 2, "vmov.x2": 1, "ldr": 4, "str": 2,
              "str[rm]": 1, "ldrd": 1, "sdiv": 1, "b": 3, "b(nt)": 1, "push{5}": 1, "pop{5,pc}": 1,
              "vpush{16}": 1, "ldr>pc": 1, "tbb": 1}
    by_hand = (10 * 2 + 10 * 1 + 10 * 1 + 3 + 2 * 14 + 2 + 4 * 2 + 2 * 1 + 2 + 3 + 12
               + 3 * (1 + REFILL) + 1 + (1 + 5) + (1 + 5 + REFILL) + (1 + 16) + (2 + REFILL) + (2 + REFILL))
    assert histogram_cycles(counts, refill=REFILL) == by_hand == 149
    assert histogram_cycles({"b": 1}, refill=3) == 4
    with pytest.raises(KeyError):
        histogram_cycles({"frobnicate": 1})


def test_stream_context_rules() -> None:
    """Load pipelining (3.3.2), an address from the instruction before, a floating-point result
    used at once (Table 7-1's note), a folded IT, and branches taken or not."""
    loads = _stream(("ldr", "r2, [r1]", 2), ("ldr", "r3, [r1, #4]", 2), ("ldr", "r4, [r3]", 2),
                    ("adds", "r1, #8", 2), ("ldr", "r5, [r1]", 2), ("str", "r5, [r1, #4]", 2))
    count = weigh(loads)
    assert count.cycles == 2 + 1 + 2 + 1 + (2 + 1) + 1
    assert count.adjustments == {"pipelined load/store": -1, "address from the instruction before": 1}
    fp = _stream(("vmul.f32", "s0, s1, s2", 4), ("vadd.f32", "s3, s3, s0", 4), ("vmul.f32", "s4, s1, s2", 4),
                 ("vmov", "r0, s3", 4), ("movs", "r1, #0", 2), ("it", "eq", 2), ("moveq", "r1, #1", 2))
    assert weigh(fp).cycles == (1 + 1) + 1 + 1 + 1 + 1 + 0 + 1
    loop = [(Instruction(0x200, 2, "subs", "r0, #1"), 0x202), (Instruction(0x202, 2, "bne.n", "200"), 0x200),
            (Instruction(0x200, 2, "subs", "r0, #1"), 0x202), (Instruction(0x202, 2, "bne.n", "200"), 0x204)]
    counted = weigh(loop, refill=3)
    assert counted.cycles == 1 + (1 + 3) + 1 + 1
    assert counted.histogram == {"sub": 2, "b": 1, "b(nt)": 1} and counted.taken_branches == 1
    pipelined = weigh(_stream(("vldr", "s0, [r0]", 4), ("vldr", "s1, [r0, #4]", 4)),
                      fp_load_store_pipelining=True)
    assert pipelined.cycles == 2 + 1
    assert weigh(_stream(("vldr", "s0, [r0]", 4), ("vldr", "s1, [r0, #4]", 4))).cycles == 4
    based = weigh(_stream(("mov", "r0, r6", 2), ("vldmia", "r0!, {s1}", 4), ("push", "{r4, lr}", 2)))
    assert based.cycles == 1 + (1 + 1 + 1) + (1 + 2)
    assert based.histogram == {"mov": 1, "vldmia{1}": 1, "push{2}": 1}


def test_flash_waits_of_a_loop_in_the_cache() -> None:
    body = _stream(*[("nop", "", 2)] * 15)
    back = Instruction(0x100 + 30, 2, "b.n", "100")
    lap = [*body, (back, 0x100)]
    waits = flash_waits([lap * 3])
    assert waits.lines_touched == 2
    assert waits.art_misses == 1  # the first line; the second is the prefetched successor
    assert waits.branches_to_another_line == 3 and waits.bound_cycles == 15


def _build(build: Path, loop_source: str, main_source: str) -> Path:
    require_target_tools()
    (build / "link.ld").write_text(image.LINKER_SCRIPT)
    (build / "startup.c").write_text(image.STARTUP)
    (build / "loop.S").write_text(loop_source)
    (build / "main.c").write_text(main_source)
    elf = build / "loop.elf"
    subprocess.run(["arm-none-eabi-gcc", *image.ARM_FLAGS, "-nostartfiles", "-T", str(build / "link.ld"),
                    str(build / "startup.c"), str(build / "loop.S"), str(build / "main.c"),
                    "-o", str(elf)], check=True, capture_output=True)
    return elf


@pytest.fixture(scope="module")
def known_loop_elf(tmp_path_factory) -> Path:
    return _build(tmp_path_factory.mktemp("known_loop"), KNOWN_LOOP, KNOWN_MAIN % ITERATIONS)


def test_known_loop_traced_in_qemu_counts_its_hand_count(known_loop_elf: Path) -> None:
    (call,) = traced_calls(known_loop_elf, "known_loop")
    assert len(call) == 8 * ITERATIONS + 1
    count = weigh(call, refill=REFILL)
    taken_lap = 2 + (3 + 1) + 1 + 2 + 1 + 1 + 1 + (1 + REFILL)
    last_lap = taken_lap - REFILL
    assert count.cycles == (ITERATIONS - 1) * taken_lap + last_lap + (1 + REFILL) == 1501
    assert count.histogram["b"] == ITERATIONS - 1 and count.histogram["b(nt)"] == 1
    assert count.adjustments == {"pipelined load/store": -ITERATIONS,
                                 "floating-point result used next": ITERATIONS}
    assert not count.unpriced
    waits = flash_waits([call])
    assert waits.lines_touched == 2  # 26 bytes from a 16-byte boundary
    assert waits.branches_to_another_line == ITERATIONS  # each bne back to the first line, and bx lr


def test_it_block_traced_in_qemu(tmp_path: Path) -> None:
    """QEMU steps through an IT block one instruction at a time, both arms included."""
    elf = _build(tmp_path, IT_LOOP, "void known_loop(unsigned n);\nint main(void) {\n    known_loop(100);\n"
                                    "    return 0;\n}\n")
    (call,) = traced_calls(elf, "known_loop")
    assert len(call) == 6 * 100 + 1
    count = weigh(call, refill=REFILL)
    assert count.histogram["it"] == 100 and count.adjustments == {"folded IT": -100}
    lap = 1 + 0 + 1 + 1 + 1 + 1
    assert count.cycles == 99 * (lap + REFILL) + lap + (1 + REFILL) == 701
