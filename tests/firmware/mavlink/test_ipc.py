"""What the flight process and the MAVLink process exchange, by field name: the events over the
socket pair and the telemetry snapshot in shared memory; a frame that is none of them is refused."""

from __future__ import annotations

import json
import mmap
import pickle
import re
import socket
import struct
from pathlib import Path

import numpy as np
import pytest

from fcemu.firmware import vehicle as v
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.loop import Command, TickSample
from fcemu.firmware.mavlink import ipc
from fcemu.firmware.mavlink.bridge import LinkedVehicle
from fcemu.firmware.mavlink.process import idle_snapshot
from fcemu.firmware.params import ParamTable
from fcemu.firmware.sensors import SensorFrame

ONE_OF_EACH = [ipc.Setpoint((0.1, 0.2, 0.3), 0.5), ipc.Sticks(0.0, 0.1, -0.1, 0.4),
               ipc.ArmRequest(True, False, 3), ipc.ModeRequest(4, 3, 7), ipc.ParamSet("FS_HOLD_T", 2.0),
               ipc.ParamSet("CTRL_SEL", 1), ipc.LinkStats({"rx_frames": 3, "ipc_bad": 0}),
               ipc.Ready({"gcs": 14550}), ipc.Ack(7, 0, ""), ipc.Text(6, "Mode HOLD"),
               ipc.FailureRequest(101, 2, 1, 9)]


def test_every_message_crosses_as_its_name_and_named_fields_and_comes_back_the_same() -> None:
    assert {type(m) for m in ONE_OF_EACH} == set(ipc.MESSAGES)
    for message in ONE_OF_EACH:
        name, fields = json.loads(ipc.encode(message))
        assert name == type(message).__name__ and list(fields) == list(message._fields)
        for field in message._fields:
            value = getattr(message, field)
            assert fields[field] == (list(value) if isinstance(value, tuple) else value), field
        back = ipc.decode(ipc.encode(message))
        assert back == message and type(back) is type(message)
        assert [type(x) for x in back] == [type(x) for x in message]


def test_a_message_is_read_by_its_field_names_not_their_order() -> None:
    frame = b'["FailureRequest",{"req":9,"instance":1,"failure_type":2,"unit":101}]'
    assert ipc.decode(frame) == ipc.FailureRequest(unit=101, failure_type=2, instance=1, req=9)
    frame = b'["Setpoint",{"thrust":0.25,"rates":[1,-0.5,0.0]}]'
    assert ipc.decode(frame) == ipc.Setpoint(rates=(1, -0.5, 0.0), thrust=0.25)


@pytest.mark.parametrize(("frame", "error"), [
    (b"", "not a message frame"),
    (b"\x00junk", "not a message frame"),
    (pickle.dumps((0, ((0.1, 0.2, 0.3), 0.5))), "not a message frame"),  # the old wire format
    (b"[" * 100_000, "not a message frame"),
    (b'{"Setpoint":{"rates":[0,0,0],"thrust":0.5}}', "not a message frame"),
    (b'["Setpoint",{"rates":[0,0,0],"thrust":0.5},1]', "not a message frame"),
    (b'["Snapshot",{}]', "unknown message 'Snapshot'"),
    (b'["__import__",{"name":"os"}]', "unknown message '__import__'"),
    (b'[0,{"rates":[0,0,0],"thrust":0.5}]', "unknown message 0"),
    (b'["Setpoint",{"rates":[0,0],"thrust":0.5}]', "Setpoint.rates: expected 3 values"),
    (b'["Setpoint",{"rates":[0,0,"x"],"thrust":0.5}]', "Setpoint.rates"),
    (b'["Setpoint",{"rates":[0,0,0],"thrust":true}]', "Setpoint.thrust: expected a number"),
    (b'["Setpoint",{"rates":[0,0,0]}]', "Setpoint: fields missing ['thrust']"),
    (b'["Setpoint",{"rates":[0,0,0],"thrust":0.5,"yaw":1}]', "unknown ['yaw']"),
    (b'["ArmRequest",{"arm":1,"force":false,"req":0}]', "ArmRequest.arm: expected a bool"),
    (b'["ModeRequest",{"main":4.0,"sub":3,"req":0}]', "ModeRequest.main: expected an int"),
    (b'["ParamSet",{"name":5,"value":1.0}]', "ParamSet.name: expected a string"),
    (b'["LinkStats",{"counters":{"rx_frames":"3"}}]', "LinkStats.counters"),
    (b'["Ready",{"ports":[14550]}]', "Ready.ports"),
])
def test_a_frame_that_is_not_a_declared_message_is_refused_saying_why(frame: bytes, error: str) -> None:
    with pytest.raises(ipc.FrameError, match=re.escape(error)):
        ipc.decode(frame)


class _Touch:
    """A pickle that creates a file when loaded: what a hostile peer could send to an unpickler."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return Path.touch, (self.path,)


def test_a_pickle_on_the_socket_is_refused_without_being_loaded(tmp_path) -> None:
    marker = tmp_path / "loaded"
    with pytest.raises(ipc.FrameError, match="not a message frame"):
        ipc.decode(pickle.dumps(_Touch(marker)))
    assert not marker.exists()


def test_a_message_whose_fields_are_not_of_their_declared_types_is_not_sent() -> None:
    with pytest.raises(ipc.FrameError, match=r"Setpoint\.rates"):
        ipc.encode(ipc.Setpoint((0.1, 0.2), 0.5))
    with pytest.raises(ipc.FrameError, match=r"Text\.severity"):
        ipc.encode(ipc.Text("6", "Mode HOLD"))
    with pytest.raises(ipc.FrameError, match="RateSetpoint is not a message"):
        ipc.encode(RateSetpoint(np.zeros(3), 0.5))


class _Hold:
    name = "hold"

    def reset(self) -> None: ...

    def update(self, setpoint, frame, dt):
        return np.full(4, 1500.0)


REST = SensorFrame(0, np.zeros(3), np.array([0.0, 0.0, -9.81]), np.zeros(4))


@pytest.fixture
def linked():
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    vehicle = v.Vehicle(ParamTable(), {"pid": _Hold()})
    slot = ipc.SnapshotSlot()
    link = LinkedVehicle(vehicle, ours, slot, every=1)
    link.command(0, REST)
    yield link, theirs, slot
    link.close()
    theirs.close()
    slot.close()


def test_the_flight_side_counts_a_bad_frame_acts_on_none_of_it_and_reads_the_next(linked) -> None:
    link, mavlink_side, _ = linked
    mavlink_side.send(b'["Sticks",{"roll":0.5,"pitch_up":0.0,"yaw":0.0}]')
    mavlink_side.send(pickle.dumps((1, (0.5, 0.0, 0.0, 0.0))))
    mavlink_side.send(ipc.encode(ipc.Sticks(roll=0.25, pitch_up=-0.5, yaw=0.125, throttle=0.0)))
    mavlink_side.send(ipc.encode(ipc.ArmRequest(arm=True, force=False, req=41)))
    link.command(1000, REST._replace(t_us=1000))
    assert link.bad_ipc == 2
    assert link.vehicle.inputs.sticks == (0.25, -0.5, 0.125, 0.0)
    ack = ipc.decode(mavlink_side.recv(65536))
    assert type(ack) is ipc.Ack and ack.req == 41 and ack.result == v.ACCEPTED and link.vehicle.armed


def _distinct_snapshot() -> ipc.Snapshot:
    """Every value different and exact in its packed type, so a field read from another's place shows."""
    fields, k = {}, 1
    for name, code, count in ipc.SNAPSHOT_LAYOUT:
        values = [float(k + i) + 0.5 if code[-1] == "f" else k + i for i in range(count)]
        fields[name] = tuple(values) if count > 1 else values[0]
        k += count
    return ipc.Snapshot(**fields)


def test_the_snapshot_is_laid_out_as_declared_and_read_back_field_by_field() -> None:
    assert [name for name, *_ in ipc.SNAPSHOT_LAYOUT] == list(ipc.Snapshot._fields)
    snap = _distinct_snapshot()
    slot = ipc.SnapshotSlot()
    slot.write(snap)
    with mmap.mmap(slot.fd, 0) as mem:  # as the MAVLink process maps it: the sequence, then the fields
        offset = 8
        for name, code, count in ipc.SNAPSHOT_LAYOUT:
            raw = struct.unpack_from(f"<{code}", mem, offset)
            assert (raw if count > 1 else raw[0]) == getattr(snap, name), name
            offset += struct.calcsize(f"<{code}")
    back = slot.read()
    for name in ipc.Snapshot._fields:
        assert getattr(back, name) == getattr(snap, name), name
    assert slot.read() is None  # read once
    slot.close()


def test_a_snapshot_field_of_the_wrong_size_is_refused_by_name_and_leaves_the_slot_as_it_was() -> None:
    slot = ipc.SnapshotSlot()
    slot.write(idle_snapshot())
    assert slot.read().pwm == (1000.0,) * 4
    with pytest.raises(ValueError, match=r"Snapshot\.gyro: 3 values, got 2"):
        slot.write(idle_snapshot()._replace(gyro=(0.0, 0.0)))
    assert slot.read() is None
    slot.write(idle_snapshot()._replace(ticks=7))
    assert slot.read().ticks == 7
    slot.close()


def test_the_flight_side_publishes_the_tick_into_the_snapshot_by_name(linked) -> None:
    link, _, slot = linked
    frame = SensorFrame(123_000, np.array([0.5, -0.25, 0.125]), np.array([0.0, 0.0, -9.5]),
                        np.array([100.0, 200.0, 300.0, 400.0]))
    command = Command(False, RateSetpoint(np.array([1.0, -2.0, 0.5]), 0.375), "pid")
    link.publish(TickSample(123_000, frame, command, np.array([1100.0, 1200.0, 1300.0, 1400.0]), "pid"))
    snap = slot.read()
    assert snap.t_us == 123_000 and snap.armed == 0 and snap.controller == 0
    assert snap.gyro == (0.5, -0.25, 0.125) and snap.accel == (0.0, 0.0, -9.5)
    assert snap.rotor_speed == (100.0, 200.0, 300.0, 400.0) and snap.pwm == (1100.0, 1200.0, 1300.0, 1400.0)
    assert snap.setpoint == (1.0, -2.0, 0.5) and snap.throttle == 0.375
    assert snap.q == pytest.approx(link.vehicle.estimator.q, abs=1e-7)
    assert snap.has_position == 0 and snap.ticks == 1
