"""The MAVLink process: every peer's link and its I/O, telemetry, parameter persistence, the tlog.

Started by `fcemu.firmware.mavlink.bridge.start_mavlink` as `python -m fcemu.firmware.mavlink.process
SPEC`; talks to the flight process over the inherited socket `SPEC["fd"]` and exits when
that closes. HEARTBEAT goes out at 1 Hz of wall time; streams follow the loop clock of the
snapshots; setpoints are coalesced (newest wins) so a flood of them costs the loop little.
What a received message means is decided by `Handlers` (firmware/mavlink/handlers.py); the
`Station` carries out what they return.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import sys
import time

from pymavlink.dialects.v20 import common as mavlink

from fcemu.firmware.mavlink import ipc, telemetry
from fcemu.firmware.mavlink import outputs as out
from fcemu.firmware.mavlink.budget import ParamStreams
from fcemu.firmware.mavlink.endpoint import Endpoint, load_signing_key
from fcemu.firmware.mavlink.handlers import Handlers
from fcemu.firmware.mavlink.replies import PendingCommands, StatusTexts
from fcemu.firmware.mavlink.signing import SigningState
from fcemu.firmware.mavlink.tlog import TlogWriter
from fcemu.firmware.params import ParamTable
from fcemu.firmware.vehicle import STABILIZED, custom_mode

M = mavlink
SETPOINT_MIN_GAP_S = 0.002  # forward at most 500 setpoint updates per second
STREAM_POLL_S = 0.002  # read the telemetry slot at 500 Hz of wall time
STATS_EVERY_S = 1.0
PARAM_SAVE_DELAY_S = 0.2
NICE = -10  # below the flight loop's -20 (timing.LOOP_NICE), above any other local process
NICE_UNPRIVILEGED = 5
REPORTED = ("rx_frames", "rx_bad", "rx_rejected", "rx_foreign", "sig_rejected", "rx_shed")


def idle_snapshot() -> ipc.Snapshot:
    zero3, zero4 = (0.0,) * 3, (0.0,) * 4
    return ipc.Snapshot(t_us=0, armed=0, custom_mode=custom_mode(STABILIZED), landed_state=1, failsafe=0,
                        controller=0, armable=0, q=(1.0, 0.0, 0.0, 0.0), gyro=zero3, accel=(0.0, 0.0, -9.81),
                        pwm=(1000.0,) * 4, rotor_speed=zero4, setpoint=zero3, throttle=0.0, position=zero3,
                        velocity=zero3, has_position=0, vz_estimate=0.0, faults=0, rejected=0, misses=0,
                        ticks=0, compute_us_max=0)


def send_health(links: list[Endpoint], stats: dict[str, int], snap: ipc.Snapshot) -> None:
    """Input health, and the loop's own deadline record, as NAMED_VALUE_INT for any ground station."""
    t_ms = (snap.t_us // 1000) & 0xFFFFFFFF
    values = [(name[:10], stats[name]) for name in REPORTED]
    values += [("loop_miss", snap.misses), ("loop_ticks", snap.ticks)]
    for ep in links:
        for name, value in values:
            ep.send(ep.mav.named_value_int_encode(t_ms, name.encode(), value & 0x7FFFFFFF))


def open_links(peers: list[dict], sysid: int, signing: SigningState | None, tlog: TlogWriter | None,
               has_position: bool) -> list[Endpoint]:
    """One link per peer. With a signing key, the links marked `signed` require it (all of them
    when none is marked)."""
    any_marked = any(p["signed"] for p in peers)
    return [Endpoint(p["name"], p["host"], int(p["port"]), sysid, i,
                     signing if p["signed"] or not any_marked else None, tlog,
                     telemetry.Scheduler(has_position))
            for i, p in enumerate(peers)]


def read_signing_key(source: str | int) -> bytes:
    """From the pipe the flight process wrote it to (bridge.open_for_mavlink), or from its file."""
    if isinstance(source, int):
        with os.fdopen(source, "rb") as pipe:
            return pipe.read()
    return load_signing_key(source)


def _restores_signal(msg) -> bool:
    """MAV_CMD_INJECT_FAILURE, MAVLink signal, OK: the one message a vehicle with its signal off hears."""
    return (msg.get_type() in ("COMMAND_LONG", "COMMAND_INT") and msg.command == M.MAV_CMD_INJECT_FAILURE
            and msg.param1 == M.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL and msg.param2 == M.FAILURE_TYPE_OK)


class Station:
    def __init__(self, config: dict, params: dict, ipc_sock: socket.socket, slot: ipc.SnapshotSlot) -> None:
        self.slot = slot
        self.sysid = int(config["sysid"])
        self.has_position = bool(config["has_position"])
        self.controllers = list(config["controllers"])
        self.params_file = config.get("params_file")
        self.params = ParamTable()
        for name, value in params.items():
            self.params.set(name, value)
        self.ipc = ipc_sock
        tlog, key_source = config.get("tlog"), config.get("signing_key")
        self.tlog = TlogWriter(tlog) if tlog not in (None, "") else None
        key = read_signing_key(key_source) if key_source not in (None, "") else None
        self.signing = SigningState(key) if key is not None else None  # one per vehicle, every link
        self.endpoints = open_links(config["peers"], self.sysid, self.signing, self.tlog, self.has_position)
        self.snap = idle_snapshot()
        self.handlers = Handlers(self.sysid, self.params, self.controllers, self.has_position,
                                   lambda: self.snap.t_us)
        self.param_streams = ParamStreams(lambda: len(self.params), self._send_param_index)
        self.counters = {"ipc_bad": 0, "snapshots": 0, "rx_signal_off": 0}
        self.pending = PendingCommands()
        self.texts = StatusTexts(self.endpoints)
        self.say = self.texts.say
        self._latest_sp: ipc.Setpoint | None = None
        self._latest_sticks: ipc.Sticks | None = None
        self._sp_sent = 0.0
        self._dirty_since: float | None = None

    # ---- what the handlers ask for ----
    def receive(self, ep: Endpoint, msg) -> None:
        if ep.muted:  # the signal is off: the one message heard is its way back
            if not _restores_signal(msg):
                self.counters["rx_signal_off"] += 1
                return
            for link in self.endpoints:
                link.muted = False
        for output in self.handlers.handle(ep, msg):
            kind = type(output)
            if kind is ipc.Setpoint:
                self._latest_sp = output
            elif kind is ipc.Sticks:
                self._latest_sticks = output
            elif kind is out.Forward:
                self._forward(ep, output)
            elif kind is out.ParamChanged:
                self._param_changed(output.name)
            elif kind is out.ParamListRequested:
                self.param_streams.request(ep, output.requester)
            elif kind is out.Say:
                self.say(output.severity, output.text, ep if output.to_sender else None, output.once,
                         output.limited)
            elif kind is out.SendTelemetry:
                self._send_one(ep, output.msgid)
            elif kind is out.MavlinkSignal:
                for link in self.endpoints:
                    link.muted = not output.on

    def _forward(self, ep: Endpoint, fwd: out.Forward) -> None:
        req = self.pending.open(ep if fwd.origin is not None else None, fwd.command, fwd.origin)
        if req is None:
            return
        # Setpoints and sticks received before the command must reach the vehicle before it: an
        # ARM right after MANUAL_CONTROL is judged on that throttle, not on the previous one.
        self._flush_setpoints(time.monotonic(), force=True)
        self._to_flight(fwd.request._replace(req=req))

    def _send_one(self, ep: Endpoint, msgid: int) -> None:
        if msgid == M.MAVLINK_MSG_ID_HEARTBEAT:
            ep.send(telemetry.heartbeat(ep.mav, self.snap))
            return
        message = telemetry.build(msgid, ep.mav, self.snap, self._load())
        if message is not None:
            ep.send(message)

    def _param_changed(self, name: str) -> None:
        self._flush_setpoints(time.monotonic(), force=True)
        self._to_flight(ipc.ParamSet(name, self.params[name]))
        for ep in self.endpoints:  # every link learns of it, as PX4 does
            self.handlers.send_param(ep, name)
        if self._dirty_since is None:
            self._dirty_since = time.monotonic()

    def _send_param_index(self, ep: Endpoint, index: int) -> None:
        names = self.params.names
        if index < len(names):
            self.handlers.send_param(ep, names[index])

    # ---- plumbing ----
    def _to_flight(self, message: ipc.Message) -> None:
        try:
            self.ipc.send(ipc.encode(message))
        except OSError:
            pass

    def _load(self) -> int:
        return min(1000, max(0, self.snap.compute_us_max))  # permille of a 1 ms tick

    def _read_ipc(self) -> bool:
        while True:
            try:
                data = self.ipc.recv(65536)
            except BlockingIOError:
                break
            except OSError:
                return False
            if not data:
                return False
            try:
                msg = ipc.decode(data)
            except ipc.FrameError:
                self.counters["ipc_bad"] += 1
                continue
            if isinstance(msg, ipc.Ack):
                self.pending.answer(msg.req, msg.result)
            elif isinstance(msg, ipc.Text):
                self.say(int(msg.severity), str(msg.text))
            else:
                self.counters["ipc_bad"] += 1
        return True

    def _stream(self) -> None:
        latest = self.slot.read()
        if latest is None:
            return
        self.counters["snapshots"] += 1
        self.snap = latest
        for ep in self.endpoints:
            for msgid in ep.scheduler.due(latest.t_us):
                message = telemetry.build(msgid, ep.mav, latest, self._load())
                if message is not None:
                    ep.send(message)

    def _housekeeping(self, now: float) -> None:
        self.pending.expire(now)
        if self._dirty_since is not None and now - self._dirty_since > PARAM_SAVE_DELAY_S:
            self._save_params()

    def _save_params(self) -> None:
        self._dirty_since = None
        if self.params_file:
            try:
                self.params.save(self.params_file)
            except OSError as exc:
                self.say(3, f"Param save failed: {exc}")

    def _flush_setpoints(self, now: float, force: bool = False) -> None:
        if (self._latest_sp or self._latest_sticks) and (force or now - self._sp_sent >= SETPOINT_MIN_GAP_S):
            for m in (self._latest_sp, self._latest_sticks):
                if m is not None:
                    self._to_flight(m)
            self._latest_sp = self._latest_sticks = None
            self._sp_sent = now

    def stats(self) -> dict:
        c = {**self.counters, **self.handlers.counters, "acks_timed_out": self.pending.timed_out}
        c["rx_frames"] = sum(ep.rx for ep in self.endpoints)
        c["rx_bad"] = sum(ep.bad for ep in self.endpoints)
        c["tx_frames"] = sum(ep.tx for ep in self.endpoints)
        c["sig_rejected"] = sum(ep.mav.signing.reject_count
                                for ep in self.endpoints if ep.signed)
        c["rx_shed"] = sum(ep.budget.shed + ep.kernel_dropped for ep in self.endpoints)
        c["param_lists_refused"] = self.param_streams.refused
        return c

    def _report(self, now: float) -> None:
        stats = self.stats()
        self._to_flight(ipc.LinkStats(stats))
        send_health(self.endpoints, stats, self.snap)
        self.texts.report_rejects(stats, now)

    def run(self) -> None:
        next_hb = time.monotonic()
        next_stats = next_hb + STATS_EVERY_S
        next_stream = next_hb
        self.ipc.setblocking(False)
        try:
            while True:
                now = time.monotonic()
                wait = min(next_hb, next_stats, next_stream) - now
                if self._latest_sp or self._latest_sticks or self.param_streams.pending():
                    wait = min(wait, SETPOINT_MIN_GAP_S)
                fds = [self.ipc, *(ep for ep in self.endpoints if ep.readable(now))]
                ready, _, _ = select.select(fds, [], [], max(0.0, wait))
                for r in ready:
                    if r is self.ipc:
                        if not self._read_ipc():
                            return
                    else:
                        for msg in r.receive(now):
                            self.receive(r, msg)
                now = time.monotonic()
                if self.param_streams.pending():
                    self.param_streams.pump(now)
                if now >= next_stream:
                    self._stream()
                    next_stream = max(next_stream + STREAM_POLL_S, now)
                self._flush_setpoints(now)
                if now >= next_hb:
                    for ep in self.endpoints:
                        ep.send(telemetry.heartbeat(ep.mav, self.snap))
                    next_hb = max(next_hb + 1.0, now)
                if now >= next_stats:
                    self._report(now)
                    next_stats = now + STATS_EVERY_S
                self._housekeeping(now)
        finally:
            self.close()

    def close(self) -> None:
        if self._dirty_since is not None:
            self._save_params()
        if self.tlog is not None:
            self.tlog.close()
        for ep in self.endpoints:
            ep.close()


def main(argv: list[str]) -> int:
    spec = json.loads(argv[1])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the flight process's; we end with it
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    # When the CPU is short (a flood of input, a busy host), the flight loop goes first, then this
    # process: a local flooder must not starve the links a flight depends on. Where raising
    # priority is not allowed the loop cannot be raised either, so this process goes below it.
    try:
        os.setpriority(os.PRIO_PROCESS, 0, NICE)
    except OSError:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, NICE_UNPRIVILEGED)
        except OSError:
            pass
    sock = socket.socket(fileno=spec["fd"])
    station = Station(spec["config"], spec["params"], sock, ipc.SnapshotSlot(spec["slot"]))
    station._to_flight(ipc.Ready({ep.name: ep.sock.getsockname()[1] for ep in station.endpoints}))
    station.run()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
