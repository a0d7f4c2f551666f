"""The instructions a function executes on the Cortex-M4 in QEMU, one by one.

QEMU runs the image with one instruction per translation block (`-singlestep`, called
`one-insn-per-tb` from QEMU 8.1 on) and logs every block it executes (`-d exec,nochain`), so
the log is the executed program-counter sequence. `arm-none-eabi-objdump -d` decodes each
address and `arm-none-eabi-nm` gives the symbols: a call of FUNCTION is the stretch from its
entry address to the first address back inside the caller, so whatever FUNCTION calls (libm,
libgcc) is counted and the caller's own instructions are not.
"""

from __future__ import annotations

import itertools
import re
import subprocess
import tempfile
from pathlib import Path

from fcemu.export.c.build import CExportError
from fcemu.export.c.cycles import FLASH_LINE_BYTES, FLASH_WAIT_STATES, Instruction, flash_waits, weigh

MACHINE = ("qemu-system-arm", "-M", "mps2-an386", "-cpu", "cortex-m4", "-nographic", "-monitor", "none",
           "-serial", "none")
TRACE_LINE = re.compile(rb"^Trace \d+: \S+ \[[0-9a-f]+/([0-9a-f]+)/", re.MULTILINE)
OBJDUMP_ADDRESS = re.compile(r"\s*[0-9a-f]+:")


def _tool(cmd: list[str], what: str, timeout: float = 300) -> str:
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        raise CExportError(f"{what} timed out after {timeout:.0f} s") from exc
    except FileNotFoundError as exc:
        raise CExportError(f"{what}: {exc}") from exc
    if done.returncode != 0:
        raise CExportError(f"{what} failed (exit {done.returncode}): {(done.stderr or done.stdout)[-2000:]}")
    return done.stdout


def disassemble(elf: Path) -> dict[int, Instruction]:
    """Every instruction of the image's code, by address."""
    out = {}
    for line in _tool(["arm-none-eabi-objdump", "-d", str(elf)], "arm-none-eabi-objdump").splitlines():
        fields = line.split("\t")
        if len(fields) < 3 or not OBJDUMP_ADDRESS.fullmatch(fields[0]) or fields[2].startswith("."):
            continue
        address, halfwords = int(fields[0].strip()[:-1], 16), fields[1].split()
        if not all(len(h) == 4 for h in halfwords):
            continue
        out[address] = Instruction(address, 2 * len(halfwords), fields[2].strip(),
                                   "\t".join(fields[3:]).strip())
    return out


def symbols(elf: Path) -> dict[str, tuple[int, int]]:
    """name → (address, size) of the image's sized symbols (Thumb bit cleared)."""
    out = {}
    for line in _tool(["arm-none-eabi-nm", "-S", str(elf)], "arm-none-eabi-nm").splitlines():
        parts = line.split()
        if len(parts) == 4:
            out[parts[3]] = (int(parts[0], 16) & ~1, int(parts[1], 16))
    return out


def _one_insn_per_tb() -> list[str]:
    options = _tool([MACHINE[0], "-help"], "qemu-system-arm -help")
    return ["-singlestep"] if "-singlestep" in options else ["-accel", "tcg,one-insn-per-tb=on"]


def executed_addresses(elf: Path, timeout: float = 300) -> list[int]:
    """The program counter of every instruction QEMU executes, from reset to the semihosting exit."""
    with tempfile.TemporaryDirectory(prefix="fcemu_trace_") as tmp:
        log = Path(tmp) / "exec.log"
        _tool([*MACHINE, *_one_insn_per_tb(), "-d", "exec,nochain", "-D", str(log), "-kernel", str(elf),
               "-semihosting-config", "enable=on,target=native"], "qemu-system-arm (trace)", timeout)
        return [int(pc, 16) for pc in TRACE_LINE.findall(log.read_bytes())]


def calls(addresses: list[int], entry: int, caller: tuple[int, int]) -> list[list[int]]:
    """Each call's addresses, from `entry` up to (and with) the first address back in `caller`
    (start, size): the last element is where execution resumed in the caller."""
    out, current = [], None
    start, size = caller
    for pc in addresses:
        if current is None:
            if pc == entry:
                current = [pc]
            continue
        current.append(pc)
        if start <= pc < start + size:
            out.append(current)
            current = None
    return out


def traced_calls(elf: Path, function: str, caller: str = "main",
                 timeout: float = 300) -> list[list[tuple[Instruction, int]]]:
    """Each call of `function` from `caller` as (instruction, address executed next) pairs."""
    code, table = disassemble(elf), symbols(elf)
    for name in (function, caller):
        if name not in table:
            raise CExportError(f"{elf.name} has no symbol {name}")
    out = []
    for call in calls(executed_addresses(elf, timeout), table[function][0], table[caller]):
        missing = [pc for pc in call[:-1] if pc not in code]
        if missing:
            raise CExportError(f"executed address {missing[0]:#x} is not in the disassembly of {elf.name}")
        out.append([(code[pc], nxt) for pc, nxt in itertools.pairwise(call)])
    if not out:
        raise CExportError(f"no complete call of {function} from {caller} in the trace of {elf.name}")
    return out


def constant_bytes(obj: Path) -> int:
    """Bytes of read-only data an object file defines (the network's weights, for the net)."""
    total = 0
    for line in _tool(["arm-none-eabi-nm", "-S", str(obj)], "arm-none-eabi-nm").splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[2] in ("r", "R"):
            total += int(parts[1], 16)
    return total


def inference_timing(elf: Path, net_object: Path, function: str = "fcemu_policy_infer",
                     top: int = 12) -> dict:
    """Cycles per call of `function`, the mean over the traced calls, weighed by `cycles.weigh`:
    `cycles` at a 2-cycle refill with VLDR/VSTR as Table 7-1 gives them; `cycles_low` (a 1-cycle
    refill, VLDR/VSTR pipelined like LDR/STR) and `cycles_high` (a 3-cycle refill) shift it by
    their difference on the last call.
    Flash (STM32F405, 5 wait states): `art_wait_cycles` in the steady state of an ART-style
    cache (`cycles.flash_waits`), `flash_bound_cycles` charging every taken branch into another
    flash line and every 16-byte line of the network's constants (read once per inference
    through the data side, whose 8-line cache cannot hold a weight matrix)."""
    runs = traced_calls(elf, function)
    counts = [weigh(run) for run in runs]

    def mean(values: list[int]) -> int:
        return round(sum(values) / len(values))

    last = counts[-1]
    flash = flash_waits(runs)
    weights = constant_bytes(net_object)
    weight_lines = -(-weights // FLASH_LINE_BYTES)
    cycles = mean([c.cycles for c in counts])
    return {
        "calls_traced": len(runs),
        "instructions": mean([c.instructions for c in counts]),
        "cycles": cycles,
        "cycles_low": weigh(runs[-1], refill=1, fp_load_store_pipelining=True).cycles - last.cycles + cycles,
        "cycles_high": weigh(runs[-1], refill=3).cycles - last.cycles + cycles,
        "taken_branches": mean([c.taken_branches for c in counts]),
        "histogram": dict(last.histogram.most_common(top)),
        "adjustments": dict(last.adjustments),
        "unpriced": dict(last.unpriced),
        "flash_wait_states": FLASH_WAIT_STATES,
        "art_misses": flash.art_misses,
        "art_wait_cycles": flash.art_cycles,
        "code_lines_touched": flash.lines_touched,
        "branches_to_another_line": flash.branches_to_another_line,
        "constant_bytes": weights,
        "flash_bound_cycles": cycles + flash.bound_cycles + weight_lines * FLASH_WAIT_STATES,
    }
