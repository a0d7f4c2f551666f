"""The flight process's side of MAVLink: a Commander and TelemetrySink around the Vehicle.

Each tick `command` drains the socket from the MAVLink process (non-blocking; nothing to
read costs one failed recv) and applies what came to the `Vehicle`; `publish` sends a
telemetry snapshot every `every` ticks (250 Hz of loop time at 1 kHz) and any text the
vehicle has to say. Sends never block: when the MAVLink process falls behind, snapshots
are dropped and counted.
"""

from __future__ import annotations

import json
import os
import select
import socket
import subprocess
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from fcemu.firmware.loop import Command, FlightLoop, TickSample
from fcemu.firmware.mavlink import ipc
from fcemu.firmware.params import CONTROLLERS
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.vehicle import Vehicle, custom_mode, mode_from_parts

READY_TIMEOUT_S = 30.0
ARMABLE_EVERY = 25  # re-run the arming checks for SYS_STATUS every this many snapshots (10 Hz)
TRUTH_EVERY = 5  # refresh ground-truth position every this many snapshots (50 Hz at 1 kHz)


@dataclass
class PeerConfig:
    name: str
    host: str
    port: int
    signed: bool = False


@dataclass
class MavlinkConfig:
    peers: list[PeerConfig] = field(default_factory=lambda: [PeerConfig("gcs", "127.0.0.1", 14550),
                                                              PeerConfig("offboard", "127.0.0.1", 14540)])
    sysid: int = 1
    tlog: str | None = None
    signing_key: str | None = None
    params_file: str | None = None
    has_position: bool = True
    controllers: list[str] = field(default_factory=lambda: list(CONTROLLERS))


def parse_peer(spec: str, name: str) -> PeerConfig:
    """host:port[:signed] (host optional: ':14550' or '14550' mean 127.0.0.1)."""
    parts = spec.split(":")
    signed = parts[-1] == "signed"
    if signed:
        parts = parts[:-1]
    host = parts[0] if len(parts) == 2 and parts[0] else "127.0.0.1"
    try:
        port = int(parts[-1])
    except ValueError:
        raise ValueError(f"bad peer {spec!r}: use host:port[:signed]") from None
    if not 0 < port < 65536 or len(parts) > 2:
        raise ValueError(f"bad peer {spec!r}: use host:port[:signed]")
    return PeerConfig(name, host, port, signed)


class Truth(Protocol):
    """Where the rig publishes a position (the free twin's ground truth, NED)."""

    position: np.ndarray
    velocity: np.ndarray


class LinkedVehicle:
    """Commander + TelemetrySink: the Vehicle, fed from and reporting to the MAVLink process."""

    def __init__(self, vehicle: Vehicle, sock: socket.socket, slot: ipc.SnapshotSlot,
                 truth: Callable[[], Truth] | None = None, every: int = 4,
                 loop: FlightLoop | None = None) -> None:
        self.vehicle = vehicle
        self.sock = sock
        self.slot = slot
        sock.setblocking(False)
        self._poll = select.poll()
        self._poll.register(sock, select.POLLIN | select.POLLHUP)
        self._armable = False
        self.truth = truth
        self.every = max(1, every)
        self.loop = loop  # for its stats in the snapshot; set after the loop is built
        self.dropped = 0
        self.bad_ipc = 0
        self.mavlink_stats: dict = {}
        self._n = 0
        self._snapshots = 0
        self._pos: tuple = (0.0, 0.0, 0.0)
        self._vel: tuple = (0.0, 0.0, 0.0)
        self._closed = False
        self._health_failsafe = ""

    # ---- Commander ----
    def command(self, t_us: int, frame: SensorFrame) -> Command:
        if not self._closed:
            self._drain()
        health = self.loop.health if self.loop is not None else None
        if health is not None and health.failsafe != self._health_failsafe:
            self._health_failsafe = health.failsafe
            if health.failsafe:
                self.vehicle.sensor_failsafe(health.failsafe)
        return self.vehicle.command(t_us, frame)

    def _drain(self) -> None:
        if not self._poll.poll(0):  # the common case: nothing new, half a µs
            return
        recv = self.sock.recv
        for _ in range(16):  # bounded: a flood cannot hold the tick
            try:
                data = recv(65536)
            except BlockingIOError:
                return
            except OSError:
                self._closed = True
                return
            if not data:
                self._closed = True
                return
            try:
                msg = ipc.decode(data)
            except ipc.FrameError:
                self.bad_ipc += 1
                continue
            self._apply(msg)

    def _apply(self, msg: ipc.Message) -> None:
        v = self.vehicle
        try:
            kind = type(msg)
            if kind is ipc.Setpoint:
                v.offboard_setpoint(msg.rates, msg.thrust)
            elif kind is ipc.Sticks:
                v.sticks(msg.roll, msg.pitch_up, msg.yaw, msg.throttle)
            elif kind is ipc.ArmRequest:
                reply = v.request_arm(bool(msg.arm), bool(msg.force))
                self._send(ipc.encode(ipc.Ack(msg.req, reply.result, reply.text)))
            elif kind is ipc.ModeRequest:
                reply = v.request_mode(mode_from_parts(int(msg.main), int(msg.sub)))
                self._send(ipc.encode(ipc.Ack(msg.req, reply.result, reply.text)))
            elif kind is ipc.ParamSet:
                v.set_param(msg.name, msg.value)
            elif kind is ipc.FailureRequest:
                reply = v.inject_failure(int(msg.unit), int(msg.failure_type), int(msg.instance))
                self._send(ipc.encode(ipc.Ack(msg.req, reply.result, reply.text)))
            elif kind is ipc.LinkStats:
                self.mavlink_stats = msg.counters
            else:
                self.bad_ipc += 1
        except (TypeError, IndexError, ValueError, KeyError):
            self.bad_ipc += 1

    # ---- TelemetrySink ----
    def publish(self, sample: TickSample) -> None:
        v = self.vehicle
        health = self.loop.health if self.loop is not None else None
        if health is not None and health.outbox:
            v.events.outbox.extend(health.outbox)
            health.outbox.clear()
        outbox = v.events.outbox
        if outbox:
            for severity, text in outbox:
                self._send(ipc.encode(ipc.Text(severity, text)))
            outbox.clear()
        self._n += 1
        if self._n % self.every or self._closed:
            return
        self._snapshots += 1
        modes = v.modes
        if self._snapshots % ARMABLE_EVERY == 1:
            self._armable = not modes.armed and not v.arming_problem()
        if self.truth is not None and self._snapshots % TRUTH_EVERY == 1:
            tr = self.truth()
            self._pos, self._vel = tuple(tr.position.tolist()), tuple(tr.velocity.tolist())
            v.position_fix(self._pos, self._vel)
        frame, sp = sample.frame, sample.command.setpoint
        loop = self.loop
        stats = loop.stats if loop is not None else None
        ticks = stats.ticks if stats is not None else self._n
        compute = int(stats.compute_us[(ticks - 1) % stats.capacity]) if stats is not None and ticks else 0
        faults = sum(loop.faults.values()) if loop is not None and loop.faults else 0
        self.slot.write(ipc.Snapshot(
            t_us=frame.t_us, armed=modes.armed, custom_mode=custom_mode(modes.mode),
            landed_state=v.landed_state, failsafe=bool(modes.failsafe),
            controller=CONTROLLERS.index(sample.controller) if sample.controller in CONTROLLERS else 255,
            armable=self._armable and not modes.armed, q=v.estimator.q, gyro=tuple(frame.gyro.tolist()),
            accel=tuple(frame.accel.tolist()), pwm=tuple(sample.pwm.tolist()),
            rotor_speed=tuple(frame.rotor_speed.tolist()), setpoint=tuple(sp.rates.tolist()),
            throttle=sp.throttle, position=self._pos, velocity=self._vel, has_position=self.truth is not None,
            vz_estimate=v.estimator.vz, faults=faults, rejected=sum(v.events.counters.values()),
            misses=stats.deadline_misses if stats else 0, ticks=ticks, compute_us_max=compute))

    def _send(self, data: bytes) -> None:
        try:
            self.sock.send(data)
        except (BlockingIOError, OSError):
            self.dropped += 1

    def close(self) -> None:
        self._closed = True
        try:
            self.sock.close()
        except OSError:
            pass


def open_for_mavlink(config: MavlinkConfig) -> dict[str, int]:
    """The MAVLink process's files, opened here so that a bad one fails in the caller, before that
    process starts: the tlog (created, emptied) and the signing key (its bytes through a pipe, not argv)."""
    files: dict[str, int] = {}
    try:
        if config.tlog:
            Path(config.tlog).parent.mkdir(parents=True, exist_ok=True)
            files["tlog"] = os.open(config.tlog, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        if config.signing_key:
            from fcemu.firmware.mavlink.endpoint import load_signing_key

            key = load_signing_key(config.signing_key)
            read_end, write_end = os.pipe()
            os.write(write_end, key)
            os.close(write_end)
            files["signing_key"] = read_end
    except BaseException:
        for fd in files.values():
            os.close(fd)
        raise
    return files


def start_mavlink(config: MavlinkConfig, params: dict[str, float]
                  ) -> tuple[subprocess.Popen, socket.socket, ipc.SnapshotSlot, dict[str, int]]:
    """Start the MAVLink process; returns it, the flight side of the socket pair, the telemetry
    slot and the process's local UDP port per peer."""
    files = open_for_mavlink(config)
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    slot = ipc.SnapshotSlot()
    for s in (ours, theirs):
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    spec = json.dumps({"config": {**asdict(config), **files}, "params": params, "fd": theirs.fileno(),
                       "slot": slot.fd})
    env = dict(os.environ)
    try:
        proc = subprocess.Popen([sys.executable, "-m", "fcemu.firmware.mavlink.process", spec],
                                pass_fds=(theirs.fileno(), slot.fd, *files.values()), env=env)
    finally:
        theirs.close()
        for fd in files.values():
            os.close(fd)
    # Wait until it is up (pymavlink imported, sockets bound) so its start-up does not land in the loop.
    ours.settimeout(READY_TIMEOUT_S)
    try:
        ready = ipc.decode(ours.recv(65536))
    except (TimeoutError, OSError, ipc.FrameError):
        ready = None
    if not isinstance(ready, ipc.Ready):
        proc.kill()
        raise RuntimeError("the MAVLink process did not start")
    ours.setblocking(False)
    return proc, ours, slot, ready.ports


def stop_mavlink(proc: subprocess.Popen, sock: socket.socket, linked: LinkedVehicle | None = None,
                 timeout: float = 3.0) -> int | None:
    if linked is not None:
        linked.close()
    else:
        sock.close()
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.terminate()
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait()
