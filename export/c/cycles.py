"""Cortex-M4 cycles for an executed Thumb-2 instruction stream, from the TRM's timing tables.

Source: ARM Cortex-M4 Processor Technical Reference Manual (ARM DDI 0439B), section 3.3
"Processor instruction timings", Table 3-1 "Cortex-M4 instruction set summary", and section
7.2.3 "FPU instruction set", Table 7-1 "FPU instruction set". Cycles per instruction:

- data processing, shifts, compare, extend, bit field, reverse, saturate, CLZ, MUL/MLA/MLS and
  the long multiplies, IT, NOP: 1. SDIV/UDIV: 2 to 12 (early termination; taken here as 12).
- LDR/LDRB/LDRH/LDRSB/LDRSH: 2; STR/STRB/STRH: 2 in Table 3-1, but 3.3.2 "Load/store
  timings" has "STR Rx,[Ry,#imm] is always one cycle", so 1 with an immediate offset and 2
  with a register offset. 3.3.2 also: an LDR, or a STR with register offset, right behind an
  LDR whose destination it does not address with takes one cycle less ("LDR [any] are
  pipelined when possible"; nothing pipelines behind a store); "any load or store that
  generates an address dependent on the result of a preceding data processing operation"
  takes one more. LDRD/STRD: 1+N = 3, never pipelined.
- LDM/STM/PUSH/POP: 1+N for N registers; with PC in a load list 1+N+P.
- B<cc>/CBZ/CBNZ: 1 if not taken, 1+P taken; B/BL/BX/BLX: 1+P; TBB/TBH: 2+P; an instruction
  that writes PC (MOV/ADD PC: 1+P, LDR PC: 2+P). P, the pipeline refill, is 1 to 3 cycles
  "depending on the alignment and width of the target instruction, and whether the processor
  manages to speculate the address early"; `refill` picks it (2 by default).
- IT: 0 when folded onto a preceding 16-bit instruction, else 1.
- FPU: VADD/VSUB/VMUL/VNMUL/VABS/VNEG/VCMP/VCVT/VMOV/VMRS/VMSR 1 (VMOV of two core registers
  2); VMLA/VMLS/VNMLA/VNMLS/VFMA/VFMS/VFNMA/VFNMS 3; VDIV/VSQRT 14; VLDR.32/VSTR.32 2,
  VLDR.64/VSTR.64 3; VLDM/VSTM/VPUSH/VPOP 1+N for N words (1+2N for N double registers).
  "Floating-point arithmetic data processing instructions, such as add, subtract, multiply,
  divide, square-root, all forms of multiply with accumulate, as well as conversions of all
  types take one cycle longer if their result is consumed by the following instruction."

What the count cannot see: a conditional instruction inside an IT block that fails its
condition is costed as if it executed (QEMU's trace shows it either way); VDIV/VSQRT are costed 14 though
integer instructions after them run on; the TRM leaves open whether VLDR/VSTR pipeline like
LDR/STR (`fp_load_store_pipelining` chooses; by default they do not, as Table 7-1 reads).

The histogram that `weigh` returns is keyed so that `histogram_cycles` of it, plus the
context adjustments it lists (a pipelined load −1, an address from the instruction before +1,
a floating-point result used at once +1, a folded IT −1), is the stream's cycle count.

`flash_waits` adds what the memory costs: an STM32F405 at 168 MHz reads flash with 5 wait
states (RM0090, "Relation between CPU clock frequency and Flash memory read time", 2.7-3.6 V)
behind its ART accelerator (64 cached 128-bit instruction lines, sequential prefetch).
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache

DEFAULT_REFILL = 2
CONDITIONS = ("eq", "ne", "cs", "hs", "cc", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt", "gt",
              "le", "al")
ONE_CYCLE = frozenset(
    "mov movw movt mvn add addw adc adr sub subw sbc rsb neg mul mla mls smull umull smlal umlal "
    "smulbb smulbt smultb smultt smulwb smulwt smlabb smlabt smlatb smlatt smlawb smlawt smmul smmla "
    "smmls smuad smusd smlad smlsd smlald smlsld umaal ssat usat ssat16 usat16 qadd qsub qdadd qdsub "
    "sadd16 ssub16 uadd16 usub16 sadd8 ssub8 uadd8 usub8 sel usad8 usada8 "
    "cmp cmn and eor orr orn bic tst teq lsl lsr asr ror rrx clz sxth sxtb uxth uxtb sxtah sxtab uxtah "
    "uxtab sxtb16 uxtb16 bfi bfc ubfx sbfx rev rev16 revsh rbit nop sev yield mrs msr cpsid cpsie dmb dsb "
    "clrex bkpt svc wfi wfe "
    "vabs vneg vadd vsub vmul vnmul vcmp vcmpe vcvt vcvtr vcvtb vcvtt vmov vmrs vmsr".split())
DIVIDE = frozenset({"sdiv", "udiv"})
LOAD_SINGLE = frozenset(
    "ldr ldrb ldrh ldrsb ldrsh ldrt ldrbt ldrht ldrsbt ldrsht ldrex ldrexb ldrexh".split())
STORE_SINGLE = frozenset("str strb strh strt strbt strht strex strexb strexh".split())
DOUBLE_WORD = frozenset({"ldrd", "strd"})
REGISTER_LIST = frozenset("ldm ldmia ldmfd ldmdb ldmea stm stmia stmea stmdb stmfd push pop".split())
FP_REGISTER_LIST = frozenset("vldm vldmia vldmdb vstm vstmia vstmdb vpush vpop".split())
FP_LOAD_STORE = frozenset({"vldr", "vstr"})
FP_MULTIPLY_ACCUMULATE = frozenset("vmla vmls vnmla vnmls vfma vfms vfnma vfnms".split())
FP_LONG = frozenset({"vdiv", "vsqrt"})
FP_RESULT_LATE = frozenset({"vadd", "vsub", "vmul", "vnmul", "vcvt", "vcvtr", "vcvtb", "vcvtt",
                            *FP_MULTIPLY_ACCUMULATE, *FP_LONG})
BRANCH = frozenset({"b", "bl", "bx", "blx", "cbz", "cbnz", "tbb", "tbh"})
ALWAYS_TAKEN = frozenset({"bl", "bx", "blx", "tbb", "tbh"})
KNOWN = ONE_CYCLE | DIVIDE | LOAD_SINGLE | STORE_SINGLE | DOUBLE_WORD | REGISTER_LIST | FP_REGISTER_LIST \
    | FP_LOAD_STORE | FP_MULTIPLY_ACCUMULATE | FP_LONG | BRANCH | {"isb", "it"}
# Instructions whose first operand is read, not only written.
FIRST_OPERAND_READ = frozenset({*STORE_SINGLE, "strd", "vstr", "vcmp", "vcmpe", "cmp", "cmn", "tst", "teq",
                                "push", "vpush", "cbz", "cbnz", "bx", "blx", *FP_MULTIPLY_ACCUMULATE,
                                "stm", "stmia", "stmea", "stmdb", "stmfd", "vstm", "vstmia", "vstmdb",
                                "movt", "bfi", "bfc"})
LIST_LOADS = frozenset({"ldm", "ldmia", "ldmfd", "ldmdb", "ldmea", "pop", "vldm", "vldmia", "vldmdb", "vpop"})
REGISTER = re.compile(r"\b(r1[0-5]|r[0-9]|s[12][0-9]|s3[01]|s[0-9]|d1[0-5]|d[0-9]|sp|lr|pc|ip|fp|sl|sb)\b")
REGISTER_RANGE = re.compile(r"\b([rsd])(\d+)-[rsd](\d+)\b")
ALIASES = {"sb": "r9", "sl": "r10", "fp": "r11", "ip": "r12", "sp": "r13", "lr": "r14", "pc": "r15"}


@dataclass(frozen=True)
class Instruction:
    """One decoded instruction as `arm-none-eabi-objdump -d` prints it."""

    address: int
    size: int
    mnemonic: str
    operands: str = ""

    def __hash__(self) -> int:  # the address alone: streams hash every executed instruction
        return self.address


@dataclass(frozen=True)
class Decoded:
    base: str
    conditional: bool
    data_types: tuple[str, ...]


@cache
def decode(mnemonic: str) -> Decoded:
    """`bne.n` → b, conditional; `vmul.f32` → vmul; `adds.w` → add; `addseq` → add; `itte` → it."""
    parts = mnemonic.lower().split(".")
    word, data_types = parts[0], tuple(p for p in parts[1:] if p not in ("n", "w"))
    if re.fullmatch(r"it[te]{0,3}", word):
        return Decoded("it", False, data_types)
    conditional = False
    stem = word[:-2]
    if word not in KNOWN and word[-2:] in CONDITIONS and (
            stem in KNOWN or (stem.endswith("s") and stem[:-1] in KNOWN)):
        word, conditional = stem, True
    if word not in KNOWN and word.endswith("s") and word[:-1] in KNOWN:
        word = word[:-1]
    return Decoded(word, conditional, data_types)


@cache
def split_operands(operands: str) -> tuple[str, ...]:
    """Operands split at top-level commas, the disassembler's comment dropped."""
    text = operands.split("@")[0].split(";")[0]
    out, depth, current = [], 0, ""
    for ch in text:
        depth += 1 if ch in "[{" else -1 if ch in "]}" else 0
        if ch == "," and depth == 0:
            out.append(current.strip())
            current = ""
        else:
            current += ch
    if current.strip():
        out.append(current.strip())
    return tuple(out)


@cache
def registers(text: str) -> frozenset[str]:
    """Register names in operand text as core r0..r15 and single-precision s0..s31 (d = two s)."""
    text = REGISTER_RANGE.sub(lambda m: ", ".join(f"{m[1]}{i}" for i in range(int(m[2]), int(m[3]) + 1)),
                              text.lower())
    found = set()
    for name in REGISTER.findall(text):
        name = ALIASES.get(name, name)
        if name[0] == "d":
            found |= {f"s{2 * int(name[1:])}", f"s{2 * int(name[1:]) + 1}"}
        else:
            found.add(name)
    return frozenset(found)


@cache
def _list_registers(operands: str) -> frozenset[str]:
    return registers(operands[operands.index("{"):]) if "{" in operands else frozenset()


@cache
def _address_registers(operands: str) -> frozenset[str]:
    return frozenset().union(*(registers(o) for o in split_operands(operands) if o.startswith("[")))


@cache
def written_and_read(ins: Instruction) -> tuple[frozenset[str], frozenset[str]]:
    """The registers an instruction writes and those it reads (flags and write-back aside)."""
    ops = split_operands(ins.operands)
    base = decode(ins.mnemonic).base
    if not ops:
        return frozenset(), frozenset()
    every = frozenset().union(*(registers(o) for o in ops))
    if base in LIST_LOADS:
        listed = _list_registers(ins.operands)
        return listed, every - listed
    if base in FIRST_OPERAND_READ:
        return frozenset(), every
    return registers(ops[0]), frozenset().union(*(registers(o) for o in ops[1:]))


def cost_key(ins: Instruction, next_address: int | None) -> str:
    """The histogram key that `histogram_cycles` prices: the mnemonic without width, condition or
    flag-setting suffix; `(nt)` on a branch not taken; `{N}` (`{N,pc}`) on a register list of N
    words; `.64` on a double-precision load or store; `.x2` on a VMOV of two core registers;
    `>pc` on a data-processing or load instruction that writes PC."""
    decoded = decode(ins.mnemonic)
    if decoded.base in BRANCH:
        may_fall_through = decoded.conditional or decoded.base in ("cbz", "cbnz")
        if may_fall_through and next_address == ins.address + ins.size:
            return f"{decoded.base}(nt)"
        return decoded.base
    return _static_key(ins)


@cache
def _static_key(ins: Instruction) -> str:
    base, ops = decode(ins.mnemonic).base, split_operands(ins.operands)
    if base in REGISTER_LIST or base in FP_REGISTER_LIST:
        listed = _list_registers(ins.operands)
        return f"{base}{{{len(listed)}{',pc' if 'r15' in listed and base in LIST_LOADS else ''}}}"
    if base in FP_LOAD_STORE:
        return f"{base}.64" if ops and ops[0].lower().startswith("d") else base
    if base == "vmov" and sum(bool(REGISTER.fullmatch(o.lower())) for o in ops) >= 3:
        return "vmov.x2"
    if ops and ops[0].lower() == "pc" and base in ONE_CYCLE | LOAD_SINGLE:
        return f"{base}>pc"
    if base in STORE_SINGLE and _register_offset(ins):
        return f"{base}[rm]"
    return base


@cache
def _base_cycles(key: str, refill: int) -> int:
    if key.endswith("(nt)"):
        return 1
    if "{" in key:
        inner = key[key.index("{") + 1:-1]
        return 1 + int(inner.split(",")[0]) + (refill if inner.endswith(",pc") else 0)
    if key.endswith(">pc"):
        return (2 if key[:-3] in LOAD_SINGLE else 1) + refill
    if key in ("tbb", "tbh"):
        return 2 + refill
    if key in BRANCH or key == "isb":
        return 1 + refill
    if key in ONE_CYCLE or key == "it":
        return 1
    if key == "vmov.x2" or key.endswith("[rm]"):
        return 2
    if key in STORE_SINGLE:
        return 1
    if key in DIVIDE:
        return 12
    if key in LOAD_SINGLE or key in STORE_SINGLE or key in FP_LOAD_STORE:
        return 2
    if key in DOUBLE_WORD or key in ("vldr.64", "vstr.64") or key in FP_MULTIPLY_ACCUMULATE:
        return 3
    if key in FP_LONG:
        return 14
    raise KeyError(key)


def histogram_cycles(counts: Mapping[str, int], refill: int = DEFAULT_REFILL) -> int:
    """Cycles of a histogram of `cost_key`s, each at its table cost (no context)."""
    return sum(n * _base_cycles(key, refill) for key, n in counts.items())


@dataclass
class CycleCount:
    """The weighed stream: cycles, instructions, the histogram and the context adjustments."""

    cycles: int = 0
    instructions: int = 0
    histogram: Counter = field(default_factory=Counter)
    adjustments: Counter = field(default_factory=Counter)
    unpriced: Counter = field(default_factory=Counter)
    taken_branches: int = 0


@cache
def _register_offset(ins: Instruction) -> bool:
    memory = [o for o in split_operands(ins.operands) if o.startswith("[")]
    return bool(memory) and "," in memory[0] and bool(REGISTER.search(memory[0].split(",", 1)[1]))


@cache
def _memory_context(prev: Instruction | None, ins: Instruction, fp_load_store: bool) -> int:
    """The 3.3.2 adjustments to a load or store: −1 for a load single behind a load whose result
    it does not address with, +1 when its address comes from the data-processing instruction
    just before."""
    loads = LOAD_SINGLE | ({"vldr"} if fp_load_store else frozenset())
    singles = loads | STORE_SINGLE | ({"vstr"} if fp_load_store else frozenset())
    here = decode(ins.mnemonic).base
    lists = REGISTER_LIST | FP_REGISTER_LIST | DOUBLE_WORD
    if prev is None or (here not in singles and here not in FP_LOAD_STORE and here not in lists):
        return 0
    before = decode(prev.mnemonic).base
    if here in ("push", "pop", "vpush", "vpop"):
        address = frozenset({"r13"})
    elif here in REGISTER_LIST or here in FP_REGISTER_LIST:
        address = registers(split_operands(ins.operands)[0])
    else:
        address = _address_registers(ins.operands)
    if before in ONE_CYCLE and not before.startswith("v") and before not in ("cmp", "cmn", "tst", "teq"):
        return 1 if written_and_read(prev)[0] & address else 0
    key = cost_key(ins, None)
    if before in loads and not cost_key(prev, None).endswith(".64") and (
            (here in loads and not key.endswith(".64")) or key.endswith("[rm]")):
        return 0 if written_and_read(prev)[0] & address else -1
    return 0


def weigh(stream: Sequence[tuple[Instruction, int | None]], refill: int = DEFAULT_REFILL,
          fp_load_store_pipelining: bool = False) -> CycleCount:
    """Cycles of an executed stream of (instruction, address executed next; None for the last)."""
    out = CycleCount()
    prev: Instruction | None = None
    for i, (ins, next_address) in enumerate(stream):
        key = cost_key(ins, next_address)
        try:
            _base_cycles(key, refill)
        except KeyError:
            out.unpriced[key] += 1
            key = "mov"  # an instruction missing from the tables is counted as one cycle
        out.histogram[key] += 1
        base = decode(ins.mnemonic).base
        if next_address is not None and next_address != ins.address + ins.size:
            out.taken_branches += 1
        memory = _memory_context(prev, ins, fp_load_store_pipelining)
        if fp_load_store_pipelining and key == "vstr":
            out.adjustments["VSTR as STR"] -= 1
        if memory:
            out.adjustments["pipelined load/store" if memory < 0 else "address from the instruction before"] \
                += memory
        if base == "it" and prev is not None and prev.size == 2:
            out.adjustments["folded IT"] -= 1
        if base in FP_RESULT_LATE and i + 1 < len(stream):
            written = registers(split_operands(ins.operands)[0])
            _, read = written_and_read(stream[i + 1][0])
            if written & read:
                out.adjustments["floating-point result used next"] += 1
        prev = ins
    out.instructions = len(stream)
    out.cycles = histogram_cycles(out.histogram, refill) + sum(out.adjustments.values())
    return out


FLASH_WAIT_STATES = 5
ART_LINES = 64
FLASH_LINE_BYTES = 16


@dataclass
class FlashWaits:
    """Flash wait cycles of the last stream given (earlier ones warm the cache)."""

    art_misses: int
    branches_to_another_line: int
    lines_touched: int
    wait_states: int

    @property
    def art_cycles(self) -> int:
        return self.art_misses * self.wait_states

    @property
    def bound_cycles(self) -> int:
        return self.branches_to_another_line * self.wait_states


def flash_waits(streams: Sequence[Sequence[tuple[Instruction, int | None]]],
                wait_states: int = FLASH_WAIT_STATES, lines: int = ART_LINES,
                line_bytes: int = FLASH_LINE_BYTES) -> FlashWaits:
    """Instruction fetches from flash behind an ART-style accelerator: `lines` cache lines of
    `line_bytes` (least recently used goes first) and a prefetch of the next sequential line.
    A fetch from a line neither cached nor the prefetched successor costs `wait_states` cycles.
    Every stream runs through the same cache; the counts are those of the last (the steady
    state when nothing else runs between inferences). The bound charges `wait_states` to every
    taken branch into another line, as if the cache held nothing."""
    cache: dict[int, None] = {}
    misses = branches = 0
    touched: set[int] = set()
    for stream in streams:
        misses = branches = 0
        touched = set()
        current = None
        for ins, next_address in stream:
            line = ins.address // line_bytes
            touched.add(line)
            if line != current:
                if line in cache:
                    cache.pop(line)
                elif current is None or line != current + 1:
                    misses += 1
                cache[line] = None
                if len(cache) > lines:
                    cache.pop(next(iter(cache)))
                current = line
            if next_address is not None and next_address != ins.address + ins.size \
                    and next_address // line_bytes != line:
                branches += 1
    return FlashWaits(misses, branches, len(touched), wait_states)
