"""Stream health for diagnostics: rates over a recent window, WARN that clears when its cause ends,
STALE when a stream stops, and topics that never received anything.

No rclpy: the node feeds it arrival times and its Ingest counters, and turns `report()` into
diagnostic_msgs. Times are `time.monotonic()` seconds (wall time: sim time may stand still).
"""
from __future__ import annotations

import enum
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

__all__ = ["HealthMonitor", "Level", "SensorReport", "StreamReport"]


_OPTIONAL = ("color",)  # a colour topic nobody publishes is logged once, it does not hold the sensor at WARN
_PAIRING_STAMPS = 64  # a depth image and its camera_info arrive within this many messages of each other


class Level(enum.IntEnum):
    """diagnostic_msgs/DiagnosticStatus levels."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass
class StreamReport:
    rate_hz: float  # messages per second over the recent window
    received: int  # messages ever
    silent_s: float  # seconds since the last message (since subscribing if none came)
    stale: bool  # it spoke, then stopped for stale_after_s
    never: bool  # subscribed for a window and nothing came
    live_s: float = 0.0  # seconds since its first message (0: none yet)


@dataclass
class SensorReport:
    level: Level
    message: str
    streams: dict[str, StreamReport] = field(default_factory=dict)
    recent_drops: dict[str, int] = field(default_factory=dict)  # reason -> drops within the window
    recent_missing: int = 0  # depth images missing within the window (gaps in the stream's stamps)


class _Stream:
    def __init__(self, now: float) -> None:
        self.subscribed_s = now
        self.arrivals: deque[float] = deque()
        self.received = 0
        self.first_s: float | None = None
        self.last_s: float | None = None


class HealthMonitor:
    """Thread-safe: subscription callbacks call `received`, the status timer the rest."""

    def __init__(self, sensors: dict[str, tuple[str, ...]], *, window_s: float, stale_after_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        """`sensors`: sensor -> the streams it subscribes to (those a report covers)."""
        self._window_s = window_s
        self.stale_after_s = stale_after_s
        self._clock = clock
        now = clock()
        # arrivals are kept from this time on (a wider window set at run time holds only the narrower one's)
        self._kept_since_s = -math.inf
        self._lock = threading.Lock()
        self._streams = {(s, stream): _Stream(now) for s, streams in sensors.items() for stream in streams}
        self._drops: dict[str, deque[tuple[float, str, int]]] = {s: deque() for s in sensors}
        self._last_dropped: dict[str, dict[str, int]] = {s: {} for s in sensors}
        self._missing: dict[str, deque[tuple[float, int]]] = {s: deque() for s in sensors}
        self._last_missing: dict[str, int] = {s: 0 for s in sensors}
        # recent header stamps of depth and camera_info, to learn whether the driver sends a camera_info
        # with every image (`_depth_short` judges only such pairs)
        self._stamps: dict[tuple[str, str], deque[int]] = {
            key: deque(maxlen=_PAIRING_STAMPS) for key in self._streams if key[1] in ("depth", "camera_info")}
        self._paired: set[str] = set()

    @property
    def window_s(self) -> float:
        return self._window_s

    @window_s.setter
    def window_s(self, value: float) -> None:
        """A new window (parameter diagnostics_window_s at run time): rates over a wider one are taken over
        the arrivals kept so far until it has passed, not as if it had none before (10x too low)."""
        with self._lock:
            if value > self._window_s:
                self._kept_since_s = max(self._kept_since_s, self._clock() - self._window_s)
            self._window_s = value

    def received(self, sensor: str, stream: str, stamp_ns: int | None = None) -> None:
        """A message arrived; stamp_ns: its header stamp (depth and camera_info)."""
        now = self._clock()
        with self._lock:
            state = self._streams.get((sensor, stream))
            if state is None:
                return
            if stamp_ns is not None and (sensor, stream) in self._stamps and sensor not in self._paired:
                other = self._stamps.get((sensor, "camera_info" if stream == "depth" else "depth"))
                if other is not None and stamp_ns in other:
                    self._paired.add(sensor)
                self._stamps[(sensor, stream)].append(stamp_ns)
            state.arrivals.append(now)
            state.received += 1
            state.first_s = now if state.first_s is None else state.first_s
            state.last_s = now
            self._expire(state.arrivals, now)

    def quiet_sensors(self, quiet_s: float) -> list[str]:
        """Sensors whose data streams (all but camera_info, which a driver may latch or keep sending)
        have all been silent for quiet_s, one of them having spoken: their streams ended (the node then
        poses what waits by extrapolation, `Ingest.stream_ends.end`)."""
        now = self._clock()
        spoke: dict[str, bool] = {}
        with self._lock:
            for (sensor, stream), state in self._streams.items():
                if stream == "camera_info" or state.last_s is None:
                    continue
                spoke[sensor] = spoke.get(sensor, True) and now - state.last_s >= quiet_s
        return [sensor for sensor, quiet in spoke.items() if quiet]

    def _expire(self, arrivals: deque, now: float) -> None:
        while arrivals and (arrivals[0] if isinstance(arrivals[0], float) else arrivals[0][0]) < now - self.window_s:
            arrivals.popleft()

    def _rate_hz(self, state: _Stream, now: float) -> float:
        """Messages per second over the window, or since the stream's first message while that is
        shorter (its intervals over their span, of a second at least: a 10 Hz camera that started 2 s
        ago is 10 Hz, not 4 Hz over a 5 s window, and a burst of its first frames is no 100 Hz)."""
        if state.first_s is not None and now - state.first_s < self.window_s and state.first_s >= self._kept_since_s:
            return (len(state.arrivals) - 1) / max(now - state.first_s, min(1.0, self.window_s))
        span = min(self.window_s, now - max(state.subscribed_s, self._kept_since_s))
        return len(state.arrivals) / span if span > 0 else 0.0

    @staticmethod
    def _take_back(missing: deque, n: int) -> None:
        """Images counted missing that were not (they came late, out of order): the newest counts in the
        window shrink by n."""
        while n > 0 and missing:
            when, count = missing.pop()
            if count > n:
                missing.append((when, count - n))
            n -= count

    def counters(self, counters: dict[str, dict[str, Any]]) -> None:
        """Ingest's counters (sensor -> {"dropped": {reason: n}, "missing_depth": n}): new drops and depth
        images found missing enter the window."""
        now = self._clock()
        with self._lock:
            for sensor, c in counters.items():
                if sensor not in self._drops:
                    continue
                before = self._last_dropped[sensor]
                for reason, n in c["dropped"].items():
                    if n > before.get(reason, 0):
                        self._drops[sensor].append((now, reason, n - before.get(reason, 0)))
                self._last_dropped[sensor] = dict(c["dropped"])
                missing = int(c.get("missing_depth", 0))
                if missing > self._last_missing[sensor]:
                    self._missing[sensor].append((now, missing - self._last_missing[sensor]))
                self._take_back(self._missing[sensor], self._last_missing[sensor] - missing)
                self._last_missing[sensor] = missing

    def report(self) -> dict[str, SensorReport]:
        now = self._clock()
        out: dict[str, SensorReport] = {}
        with self._lock:
            for sensor, drops in self._drops.items():
                self._expire(drops, now)
                recent: dict[str, int] = {}
                for _, reason, n in drops:
                    recent[reason] = recent.get(reason, 0) + n
                self._expire(self._missing[sensor], now)
                missing = sum(n for _, n in self._missing[sensor])
                streams = {}
                for (s, stream), state in self._streams.items():
                    if s != sensor:
                        continue
                    self._expire(state.arrivals, now)
                    silent = now - (state.last_s if state.last_s is not None else state.subscribed_s)
                    streams[stream] = StreamReport(
                        rate_hz=self._rate_hz(state, now), received=state.received, silent_s=silent,
                        stale=state.last_s is not None and silent > self.stale_after_s,
                        never=state.last_s is None and silent > self.window_s,
                        live_s=0.0 if state.first_s is None else now - state.first_s)
                out[sensor] = self._judge(streams, recent, missing, window_s=self.window_s,
                                          paired=sensor in self._paired)
        return out

    @staticmethod
    def _judge(streams: dict[str, StreamReport], recent: dict[str, int], missing: int, *, window_s: float,
               paired: bool) -> SensorReport:
        # camera_info may come once (a latched publisher): its silence while depth comes is no stop
        depth_live = "depth" in streams and not streams["depth"].stale and not streams["depth"].never
        stale = sorted(name for name, r in streams.items() if r.stale and not (name == "camera_info" and depth_live))
        never = sorted(name for name, r in streams.items() if r.never and name not in _OPTIONAL)
        short = paired and _depth_short(streams, window_s)
        if stale:
            level = Level.STALE
            message = f"no messages on {', '.join(stale)} for {max(streams[n].silent_s for n in stale):.1f} s"
        elif never or recent or missing or short:
            level = Level.WARN
            parts = []
            if never:
                parts.append(f"nothing received yet on {', '.join(never)}")
            if recent:
                parts.append("recently dropped: " + ", ".join(f"{n} {r}" for r, n in sorted(recent.items())))
            if short:
                parts.append(f"depth {streams['depth'].rate_hz:.1f} Hz against camera_info "
                             f"{streams['camera_info'].rate_hz:.1f} Hz: most depth images are lost on the way (large "
                             "images over best-effort QoS, or the transport's shared memory too small?)")
            elif missing:
                parts.append(f"recently missing: {missing} depth image(s) (gaps in the depth stamps)")
            message = "; ".join(parts)
        else:
            level = Level.OK
            message = ", ".join(f"{name} {r.rate_hz:.1f} Hz" for name, r in streams.items() if not r.never) or "ok"
        return SensorReport(level, message, streams, recent, missing)


def _depth_short(streams: dict[str, StreamReport], window_s: float) -> bool:
    """Depth arriving at under half the rate of its camera_info (judged where the driver publishes a
    camera_info with every image, stamped as the image: a small message the transport rarely loses),
    both live for the whole window (a stream that began within it has its rate taken over time it was
    not there)."""
    depth, info = streams.get("depth"), streams.get("camera_info")
    return (depth is not None and info is not None and not depth.stale and not info.stale
            and min(depth.live_s, info.live_s) >= window_s and info.rate_hz >= 1.0
            and depth.rate_hz < 0.5 * info.rate_hz)
