"""`fcemu sitl -i N`, as PX4 SITL's instances: system id 1+N, offboard peer 14540+N, the GCS
peer shared, a parameter file each; two vehicles flown at once share and clobber nothing."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M

from fcemu.sitl.cli import register
from fcemu.sitl.sitl import mavlink_config_from_args
from tests.firmware.mavlink.conftest import ROOT, listen

CLIMB = 0.85  # thrust 0..1, above the Iris's hover


def parse(*argv: str):
    import argparse

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return parser.parse_args(["sitl", *argv])


def test_instance_offsets_follow_px4(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    zero, three = mavlink_config_from_args(parse()), mavlink_config_from_args(parse("-i", "3"))
    assert zero.sysid == 1 and three.sysid == 4
    assert [(p.name, p.port) for p in zero.peers] == [("gcs", 14550), ("offboard", 14540)]
    assert [(p.name, p.port) for p in three.peers] == [("gcs", 14550), ("offboard", 14543)]
    assert zero.params_file == str(tmp_path / "fcemu" / "params.json")
    assert three.params_file == str(tmp_path / "fcemu" / "params-3.json")
    explicit = mavlink_config_from_args(parse("-i", "3", "--sysid", "9", "--offboard", ":15000",
                                              "--params", ""))
    assert (explicit.sysid, explicit.peers[1].port, explicit.params_file) == (9, 15000, None)
    for bad in ("255", "-1", "one"):  # system id 1+N must stay a MAVLink system id
        with pytest.raises(SystemExit):
            parse("-i", bad)


class Peer:
    """One vehicle's offboard peer: its own UDP port, addressing the vehicle's system id."""

    def __init__(self, port: int, sysid: int) -> None:
        self.sysid = sysid
        self.conn = listen_conn(port)
        self.heartbeats: list = []
        self.positions: list = []
        self.acks: list = []
        self.texts: list[str] = []

    def pump(self, thrust: float | None) -> None:
        """Read what came; stream a setpoint once the vehicle has been heard (and the MAVLink
        version with it)."""
        if thrust is not None and self.heartbeats:
            self.conn.mav.set_attitude_target_send(0, self.sysid, 1, 128, [1, 0, 0, 0], 0, 0, 0, thrust)
        while (m := self.conn.recv_msg()) is not None:
            kind = m.get_type()
            if kind == "HEARTBEAT":
                self.heartbeats.append(m)
                del self.heartbeats[:-1]
            elif kind == "LOCAL_POSITION_NED":
                self.positions.append(m)
            elif kind == "COMMAND_ACK":
                self.acks.append(m)
            elif kind == "STATUSTEXT":
                self.texts.append(m.text)

    def state(self) -> tuple[str, bool] | None:
        if not self.heartbeats:
            return None
        hb = self.heartbeats[-1]
        return (mavutil.interpret_px4_mode(hb.base_mode, hb.custom_mode),
                bool(hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED))

    def command(self, cmd: int, *params: float) -> None:
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        self.conn.mav.command_long_send(self.sysid, 1, cmd, 0, *p)


def listen_conn(port: int):
    from tests.firmware.mavlink.conftest import _LISTENERS

    conn = _LISTENERS.pop(port)
    conn.source_system = conn.mav.srcSystem = 255
    return conn


def fly_together(peers: list[Peer], seconds: float, thrust: float | None) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for peer in peers:
            peer.pump(thrust)
        time.sleep(0.02)


def until(peers: list[Peer], cond, thrust: float | None, timeout: float = 20.0, ask=None) -> None:
    """Fly until `cond` holds for every peer; `ask(peer)` (a command) is repeated each second to
    the peers it does not hold for yet, as a ground station retries."""
    end, next_ask = time.monotonic() + timeout, 0.0
    while not all(cond(p) for p in peers):
        assert time.monotonic() < end, [(p.sysid, p.state(), [(a.command, a.result) for a in p.acks],
                                         p.texts[-6:]) for p in peers]
        if ask is not None and time.monotonic() >= next_ask:
            for peer in peers:
                if not cond(peer):
                    ask(peer)
            next_ask = time.monotonic() + 1.0
        fly_together(peers, 0.1, thrust)


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_two_instances_fly_at_once_with_their_own_ids_ports_and_parameters(tmp_path) -> None:
    gcs_port = listen()  # one ground station for both, as QGC on 14550 sees every PX4 instance
    offboard = [listen(), listen()]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "XDG_DATA_HOME": str(tmp_path)}
    procs = [subprocess.Popen([sys.executable, "-m", "fcemu.cli", "sitl", "-i", str(n), "--controller", "pid",
                               "--quiet", "--duration", "150", "--gcs", f"127.0.0.1:{gcs_port}",
                               "--offboard", f"127.0.0.1:{offboard[n]}"],
                              cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for n in (0, 1)]
    try:
        peers = [Peer(offboard[n], 1 + n) for n in (0, 1)]
        until(peers, lambda p: p.heartbeats, None, timeout=60)
        assert [{m.get_srcSystem() for m in p.heartbeats} for p in peers] == [{1}, {2}]
        gcs = listen_conn(gcs_port)
        seen: set[int] = set()
        deadline = time.monotonic() + 10
        while seen != {1, 2} and time.monotonic() < deadline:
            fly_together(peers, 0.02, 0.0)
            m = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=0.05)  # bounded: both keep sending
            if m is not None:
                seen.add(m.get_srcSystem())
        assert seen == {1, 2}

        # a parameter set on each instance (by its own peer) lands in that instance's own file;
        # the setpoint-loss timeouts set are long, so a busy host that stalls a peer for a moment
        # does not send a vehicle to LAND
        files = [tmp_path / "fcemu" / "params.json", tmp_path / "fcemu" / "params-1.json"]
        for n, value in ((1, 5.0), (0, 4.0)):
            path = files[n]
            deadline, next_ask = time.monotonic() + 10, 0.0
            while not path.exists() and time.monotonic() < deadline:
                if time.monotonic() >= next_ask:  # asked again each second, as a ground station retries
                    peers[n].conn.mav.param_set_send(1 + n, 1, b"COM_OF_LOSS_T", value,
                                                     M.MAV_PARAM_TYPE_REAL32)
                    next_ask = time.monotonic() + 1.0
                fly_together(peers, 0.05, 0.0)
            assert json.loads(path.read_text())["COM_OF_LOSS_T"] == pytest.approx(value)
        assert json.loads(files[1].read_text())["COM_OF_LOSS_T"] == pytest.approx(5.0)

        # each peer arms its own vehicle in OFFBOARD and climbs
        fly_together(peers, 0.5, 0.0)  # a setpoint stream first, as PX4 asks
        until(peers, lambda p: p.state()[0] == "OFFBOARD", 0.0,  # PX4's custom main mode 6
              ask=lambda p: p.command(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6))
        until(peers, lambda p: p.state() == ("OFFBOARD", True), 0.0,
              ask=lambda p: p.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1))
        for peer in peers:
            peer.positions.clear()
        until(peers, lambda p: p.positions and p.positions[-1].z < -1.0, CLIMB)
        assert [p.state() for p in peers] == [("OFFBOARD", True)] * 2
    finally:
        outputs = []
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
            try:
                outputs.append("".join(proc.communicate(timeout=20)))
            except subprocess.TimeoutExpired:
                proc.kill()
                outputs.append("".join(proc.communicate()))
    for out in outputs:
        assert "fcemu: flying pid" in out and "Traceback" not in out, out[-2000:]
    assert sorted(p.name for p in (tmp_path / "fcemu").iterdir()) == ["params-1.json", "params.json"]
