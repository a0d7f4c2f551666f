"""Progress on stderr with an estimate of the time left, for the commands that run for minutes
(`fcemu identify`'s closed-loop refinement, `fcemu fit`'s stages).

`Counted` is work of many like items (flights): a tqdm bar where the stream is a terminal, elsewhere
(a log file, a pipe) a line at each quarter. `Stages` is a command's few unlike stages, each with
the seconds it is expected to take, logged as each starts. Either way the time left is an estimate
and says so.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Collection, Mapping
from typing import Any, TextIO


def duration(seconds: float) -> str:
    """'45 s', '3 min 20 s', '14 min': as precise as an estimate of that size is worth."""
    s = max(0, round(seconds))
    if s < 90:
        return f"{s} s"
    minutes, s = divmod(s, 60)
    return f"{minutes} min" if minutes >= 10 else f"{minutes} min {s} s"


def left_text(seconds: float | None) -> str:
    if seconds is None:
        return "time left not yet known"
    return "less than a second left" if seconds < 0.5 else f"about {duration(seconds)} left, an estimate"


def is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class Counted:
    """`total` like items done one after another (`total` at most where the work may end early): the
    time left is the time per item so far times the items left. `update(done, total)` may revise the
    total as the work learns how much is left."""

    def __init__(self, desc: str, total: int, unit: str, stream: TextIO | None = None, lines: int = 4,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.desc, self.total, self.unit, self.lines, self.clock = desc, max(1, total), unit, lines, clock
        self.stream = stream or sys.stderr
        self.t0, self.done, self.shown = clock(), 0, 0
        self.bar = None
        if is_terminal(self.stream):
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, desc=desc, unit=unit, file=self.stream, leave=False)

    def left(self) -> float | None:
        if self.done == 0:
            return None
        return (self.clock() - self.t0) / self.done * max(self.total - self.done, 0)

    def update(self, done: int, total: int | None = None, note: str = "") -> None:
        self.done = done
        self.total = max(total or self.total, done, 1)  # an optimiser may overrun its plan by a step
        if self.bar is not None:
            self.bar.total = self.total
            self.bar.set_postfix_str(note, refresh=False)
            self.bar.update(done - self.bar.n)
            return
        quarter = done * self.lines // self.total
        if quarter > self.shown and done < self.total:
            self.shown = quarter
            note = f", {note}" if note else ""
            self.stream.write(f"  {self.desc}: {done}/{self.total} {self.unit}s{note}; "
                              f"{duration(self.clock() - self.t0)} so far; {left_text(self.left())}\n")
            self.stream.flush()

    def close(self) -> float:
        """The seconds it took; the bar cleared, one line saying so."""
        took = self.clock() - self.t0
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        self.stream.write(f"  {self.desc}: {self.done} {self.unit}s in {duration(took)}\n")
        self.stream.flush()
        return took

    def __enter__(self) -> Counted:
        return self

    def __exit__(self, kind: type[BaseException] | None, *rest: object) -> None:
        if kind is None:
            self.close()
        elif self.bar is not None:  # the error says what happened; the bar only goes
            self.bar.close()


class Stages:
    """A command's stages, each expected to take `expected[stage]` seconds. The time left is what the
    stages not yet finished are expected to take, those in `calibrate` scaled by the pace of the
    finished ones in it (their seconds over their expectation: how fast this machine is today), less
    what the current stage has used. Stages outside `calibrate` take what they take on any machine
    (a budget of seconds, a flight against the wall clock)."""

    def __init__(self, expected: Mapping[str, float], log: Callable[[str], Any],
                 calibrate: Collection[str] = (), clock: Callable[[], float] = time.monotonic) -> None:
        self.expected, self.log, self.calibrate, self.clock = dict(expected), log, set(calibrate), clock
        self.t0 = clock()
        self.took: dict[str, float] = {}
        self.current: str | None = None
        self.started = self.t0

    def expect(self, stage: str, seconds: float) -> None:
        self.expected[stage] = seconds

    def skip(self, stage: str) -> None:
        self.expected.pop(stage, None)

    def pace(self) -> float:
        timed = [s for s in self.took if s in self.calibrate and self.expected.get(s, 0.0) > 0.0]
        if not timed:
            return 1.0
        return sum(self.took[s] for s in timed) / sum(self.expected[s] for s in timed)

    def left(self) -> float:
        pace = self.pace()

        def seconds(stage: str) -> float:
            return self.expected[stage] * (pace if stage in self.calibrate else 1.0)

        rest = sum(seconds(s) for s in self.expected if s not in self.took and s != self.current)
        if self.current in self.expected:
            rest += max(seconds(self.current) - (self.clock() - self.started), 0.0)
        return rest

    def elapsed(self) -> float:
        return self.clock() - self.t0

    def finish(self) -> None:
        if self.current is not None:
            self.took[self.current] = self.clock() - self.started
            self.current = None

    def start(self, stage: str, text: str | None) -> None:
        """The current stage finished, `stage` begun: `text` logged with the time so far and left
        (nothing where it is None)."""
        self.finish()
        self.current, self.started = stage, self.clock()
        if text is not None:
            self.note(text)

    def note(self, text: str) -> None:
        self.log(f"[{self.elapsed():5.0f} s] {text}; {left_text(self.left())}")
