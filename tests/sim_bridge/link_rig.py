"""What the lockstep link's tests share: a real UDP relay that loses, duplicates and delays packets
(`LossyProxy`), the reference frames of the in-process twin, and the comparisons."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.link import InProcessLink, Transport, UdpTwinClient
from fcemu.sim_bridge.twin import SensorNoise, Twin, TwinState

TIMEOUT = 0.05  # client retry period for these tests: short, so loss costs little wall time
NOISE = SensorNoise(gyro_std=0.05, gyro_bias=(0.01, -0.02, 0.03), accel_std=0.3, rotor_speed_std=4.0)
START = TwinState(attitude=(0.99, 0.05, -0.08, 0.1), body_rates=(0.5, -1.0, 2.0),
                  rotor_speed=(700.0, 750.0, 800.0, 850.0), position=(0.0, 0.0, -3.0))


def pwm_sequence(n: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(1000.0, 2000.0, size=(n, 4))


def run(link: Transport, pwms: np.ndarray, seed: int | None = 7,
        state: TwinState | None = None) -> list[SensorFrame]:
    return [link.reset(seed, state)] + [link.pwm_write(p) for p in pwms]


def assert_identical(got: list[SensorFrame], expected: list[SensorFrame]) -> None:
    assert len(got) == len(expected)
    for i, (a, b) in enumerate(zip(got, expected, strict=True)):
        assert a.t_us == b.t_us, f"frame {i}"
        for name, x, y in zip(("gyro", "accel", "rotor_speed"), a[1:4], b[1:4], strict=True):
            assert x.tobytes() == y.tobytes(), f"frame {i} {name}: {x} != {y}"
        assert a.gyro_t_us == b.gyro_t_us, f"frame {i} gyro_t_us"
        x, y = a.rotor_speed_t_us, b.rotor_speed_t_us
        assert (x is None and y is None) or (x is not None and y is not None and x.dtype == y.dtype
                                             and x.tobytes() == y.tobytes()), f"frame {i} rotor_speed_t_us"


def reference(pwms: np.ndarray, rig: str = "rig", noise: SensorNoise | None = None, seed: int | None = 7,
              state: TwinState | None = None) -> list[SensorFrame]:
    return run(InProcessLink(Twin(rig=rig, noise=noise)), pwms, seed, state)


def client_of(address: tuple[str, int], retries: int = 20) -> UdpTwinClient:
    return UdpTwinClient(*address, timeout=TIMEOUT, retries=retries)


def wait_for(condition, seconds: float = 2.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "condition never became true"
        time.sleep(0.005)


class LossyProxy:
    """A UDP relay that drops, duplicates or delays the n-th request or reply (0-based)."""

    def __init__(self, server: tuple[str, int], drop_requests=(), drop_replies=(), duplicate_requests=(),
                 duplicate_replies=(), delay_requests: dict[int, float] | None = None) -> None:
        self.server = server
        self.rules = {"request": (set(drop_requests), set(duplicate_requests), delay_requests or {}),
                      "reply": (set(drop_replies), set(duplicate_replies), {})}
        self.seen = {"request": 0, "reply": 0}
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.connect(server)
        self.client: tuple[str, int] | None = None
        self._stop = False
        self._threads = [threading.Thread(target=self._relay, args=(self.front, "request"), daemon=True),
                         threading.Thread(target=self._relay, args=(self.back, "reply"), daemon=True)]
        for sock in (self.front, self.back):
            sock.settimeout(0.02)
        for thread in self._threads:
            thread.start()

    @property
    def address(self) -> tuple[str, int]:
        return self.front.getsockname()

    def _relay(self, sock: socket.socket, direction: str) -> None:
        drop, duplicate, delay = self.rules[direction]
        while not self._stop:
            try:
                data, addr = sock.recvfrom(2048)
            except (TimeoutError, OSError):
                continue
            index = self.seen[direction]
            self.seen[direction] += 1
            if direction == "request":
                self.client = addr
                forward = self.back.send
            else:
                forward = lambda d: self.front.sendto(d, self.client)  # noqa: E731
            if index in drop:
                continue
            copies = 2 if index in duplicate else 1
            if index in delay:
                threading.Timer(delay[index], forward, args=(data,)).start()
                continue
            for _ in range(copies):
                forward(data)

    def close(self) -> None:
        self._stop = True
        for thread in self._threads:
            thread.join()
        self.front.close()
        self.back.close()
