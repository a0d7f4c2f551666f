"""MAVLink 2 signature checking, one state per key shared by every link of the vehicle.

What the MAVLink C library's `mavlink_signature_check` does, in the same order: the HMAC is
verified before anything is looked up or remembered, so a frame that is not signed with the key
changes nothing. Then the timestamp must be newer than the last one accepted for its stream
(link_id, system, component), or, for a stream not seen before, at most a minute older than
the vehicle's own clock. The stream table is the vehicle's, not a link's: a signed frame
captured on one link is a replay on every other link too.

pymavlink's own `MAVLink.check_signature` stores the stream's timestamp before it compares the
HMAC, so one forged frame stamped near 2^48 locks the real key holder out; it is replaced on
each link's parser by `SigningState.check`.
"""

from __future__ import annotations

import hashlib
import hmac
import time

SIGNING_EPOCH = 1420070400  # 2015-01-01, MAVLink 2 signing timestamps count 10 µs from here
NEW_STREAM_MAX_AGE = 6_000_000  # one minute, in 10 µs
MAX_STREAMS = 64  # only key holders can add one; a bound all the same


def signing_now() -> int:
    return int((max(time.time(), SIGNING_EPOCH) - SIGNING_EPOCH) * 100_000)


class SigningState:
    def __init__(self, key: bytes) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink 2 signing key is 32 bytes")
        self.key = key
        self.timestamp = signing_now()
        self.streams: dict[tuple[int, int, int], int] = {}
        self.bad_signature = self.replayed = self.too_old = 0

    def check(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        """pymavlink's `check_signature` contract: `msgbuf` is the whole frame, signature last."""
        digest = hashlib.sha256(self.key + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            self.bad_signature += 1
            return False
        link_id = msgbuf[-13]
        stamp = int.from_bytes(msgbuf[-12:-6], "little")
        stream = (link_id, src_system, src_component)
        last = self.streams.get(stream)
        if last is not None:
            if stamp <= last:
                self.replayed += 1
                return False
        else:
            now = max(self.timestamp, signing_now())
            if stamp + NEW_STREAM_MAX_AGE < now or len(self.streams) >= MAX_STREAMS:
                self.too_old += 1
                return False
        self.streams[stream] = stamp
        self.timestamp = max(self.timestamp, stamp)
        return True
