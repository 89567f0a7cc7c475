"""Stream timelines: which message stamps are on time, and when time has restarted.

Each stream (a sensor's depth, colour or pose messages) keeps a timeline: its newest accepted
stamp. A stamp more than `time_jump_s` behind its stream's timeline, or ahead of the newest stamp
of all streams, is off it (a glitching driver, one bad message, an unset stamp 0): rejected as
`bad_stamp`, it moves no timeline. Such stamps are remembered as candidates of a new timeline: once
every stream that spoke since the first candidate has continued on it for `restart_confirm_msgs`
messages, spanning `restart_confirm_s`, time has restarted (a bag looping, a robot restarting its
clock) and the streams move to the new timeline: back (the caller flushes what waits) or ahead
(every stream resumed after a pause; one clock, so a stream yet to speak keeps its timeline). A
stream that speaks on the old timeline meanwhile ends that episode if it had moved to the new one
(a glitch) or stays on the old one for more than `time_jump_s`; otherwise its messages were in
flight when time restarted (a busy reader hands them over late), and it must move too before the
restart is confirmed (unless the new timeline goes on without it for more than `time_jump_s`: it
stopped). The candidates' messages, held meanwhile (the
newest `hold_msgs` per stream), are handed back with the restart, so the new timeline loses none of
its start. A restart known from outside (`restart`: the /clock went back) starts every timeline
again from its time, so that old messages still in flight are off it; the new time's messages that
came before the news are handed back with it. After either, a message of
the old time that was still in flight (until the new timeline has gone on for `time_jump_s`) is
rejected as `time_jump`, the restart's loss, not as a bad stamp. A depth stamp must be new
(not among the stream's latest) and move forward, except one between the stream's two newest (or older
than its only one): that newest was stamped ahead of its place (or two frames crossed), and the
stream's time goes back.
Decisions depend on stamps and their order alone, never on the wall clock.

`Timelines` is not thread-safe: its owner (`ingest.Ingest`) calls it under its lock.
"""
from __future__ import annotations

import bisect
import statistics
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["STREAMS", "ClockTimeline", "Gap", "Held", "Restart", "StreamGaps", "Timelines", "Verdict"]

STREAMS: tuple[str, ...] = ("depth", "color", "pose")
_RECENT_DEPTH_STAMPS = 16  # a depth stamp among this many taken lately is a duplicate
# StreamGaps: an interval of this many of a stream's periods lost images (a camera's jitter stays far below it); the
# period is the median of the last _PERIOD_INTERVALS intervals, once there are _MIN_INTERVALS
_GAP_PERIODS = 1.8
_PERIOD_INTERVALS = 16
_MIN_INTERVALS = 8
_COUNTED_GAPS = 4  # StreamGaps: the latest gaps into which images may still come late (out of order)
# StreamGaps: this many gaps in a row, each within _STEADY_RATIO of the others and none filled by a late image,
# are a stream whose rate went down
_RATE_CHANGE_GAPS = 16
_STEADY_RATIO = 1.25


@dataclass(frozen=True)
class Held:
    """A message rejected as bad_stamp while it was a candidate of a new timeline: what `check` got."""

    sensor: str
    stream: str
    stamp_ns: int
    message: Any


@dataclass(frozen=True)
class Restart:
    """Time restarted at `to_ns`; the newest stamp before was `from_ns` (None: no stamp yet)."""

    to_ns: int
    from_ns: int | None
    # the new timeline's earlier messages, rejected as bad_stamp until now, in stamp order: the caller
    # takes them as on time
    held: tuple[Held, ...] = ()
    # (sensor, stream) -> how many more of its messages, rejected as bad_stamp, were the new timeline's
    # start but were not held (past hold_msgs): lost to the restart
    lost: dict[tuple[str, str], int] = field(default_factory=dict)
    # the old timeline took fewer than restart_confirm_msgs messages: its first stamps were strays (a driver's
    # first stamp far off), not a time that restarted
    stray_start: bool = False

    @property
    def went_back(self) -> bool:
        return self.from_ns is not None and self.to_ns < self.from_ns


@dataclass(frozen=True)
class Verdict:
    """What a stamp is: on time (reason None), or rejected with `reason` ("bad_stamp", "time_jump": of the
    time before a restart, "duplicate", "out_of_order"; `error` says what was wrong with the stamp). A
    rejected stamp can also have confirmed a restart, which the timelines already moved to; the
    message that confirmed it is on time (reason None) when it is the newest of its stream."""

    reason: str | None = None
    error: str = ""
    restart: Restart | None = None


class Timelines:
    """The newest accepted stamp per sensor and stream, and the candidates of a new timeline."""

    def __init__(self, sensors: tuple[str, ...], *, time_jump_s: float, restart_confirm_msgs: int,
                 restart_confirm_s: float, hold_msgs: Mapping[str, int]) -> None:
        self._last_ns: dict[tuple[str, str], int | None] = {(s, stream): None for s in sensors for stream in STREAMS}
        # a new timeline in the making: per stream, its consistent off-timeline stamps, the newest of
        # their messages, and whether the stream spoke since the first of them
        self._candidates: dict[tuple[str, str], list[int]] = {key: [] for key in self._last_ns}
        self._held: dict[tuple[str, str], deque[Held]] = {key: deque() for key in self._last_ns}
        self.configure(time_jump_s=time_jump_s, restart_confirm_msgs=restart_confirm_msgs,
                       restart_confirm_s=restart_confirm_s, hold_msgs=hold_msgs)
        self._spoke: dict[tuple[str, str], bool] = {key: False for key in self._last_ns}
        # streams that spoke on the old timeline since the first candidate, without candidates of their
        # own: the stamp of their first such message, and the new timeline's newest stamp when they last
        # spoke. Each must move to the new timeline before a restart is confirmed (unless it stopped); one
        # that stays on the old one for longer than time_jump_s ends the episode
        self._lagging: dict[tuple[str, str], tuple[int, int]] = {}
        # depth streams: the stamps taken lately (duplicates), and the newest before the newest (order)
        self._recent_depth_ns: dict[tuple[str, str], deque[int]] = {
            key: deque(maxlen=_RECENT_DEPTH_STAMPS) for key in self._last_ns if key[1] == "depth"}
        self._previous_depth_ns: dict[tuple[str, str], int] = {}
        # where time restarted, known from outside (the /clock): the timeline until a stream has one
        self._anchor_ns: int | None = None
        # after a restart: the old timeline's newest stamp and the new one's when it restarted (`_in_flight`)
        self._old_time: tuple[int, int] | None = None
        self._taken = 0  # messages on time since the timelines last moved (`Restart.stray_start`)

    def configure(self, *, time_jump_s: float, restart_confirm_msgs: int, restart_confirm_s: float,
                  hold_msgs: Mapping[str, int]) -> None:
        """The limits (see the module's docstring; `hold_msgs` per stream kind); the timelines stay."""
        self._far_ns = int(time_jump_s * 1e9)
        self._confirm_msgs = restart_confirm_msgs
        self._confirm_ns = restart_confirm_s * 1e9
        for key, held in self._held.items():
            self._held[key] = deque(held, maxlen=max(1, hold_msgs[key[1]]))

    def last_ns(self, sensor: str, stream: str) -> int | None:
        """The stream's newest accepted stamp."""
        return self._last_ns[(sensor, stream)]

    def depth_floor_ns(self, sensor: str) -> int | None:
        """The stamp the sensor's next depth image must be newer than to be taken (the stream's second
        newest: `_depth_order`), or None when any may be."""
        return self._previous_depth_ns.get((sensor, "depth"))

    def sensor_now_ns(self, sensor: str) -> int | None:
        """The sensor's stream time: the newest stamp accepted on any of its streams."""
        stamps = [t for (s, _), t in self._last_ns.items() if s == sensor and t is not None]
        return max(stamps) if stamps else None

    def now_ns(self) -> int | None:
        """The newest accepted stamp of any stream, or where time restarted (`restart`)."""
        stamps = [t for t in (*self._last_ns.values(), self._anchor_ns) if t is not None]
        return max(stamps) if stamps else None

    def check(self, sensor: str, stream: str, stamp_ns: int, message: Any = None) -> Verdict:
        """Where a stamp stands against its stream's timeline; the timeline moves when it is on time.
        Depth stamps must also move forward (`duplicate`, `out_of_order`). `message` is held while
        the stamp is a candidate of a new timeline (see `Restart.held`)."""
        key = (sensor, stream)
        last, now = self._last_ns[key], self.now_ns()
        behind = last is not None and stamp_ns < last - self._far_ns
        ahead = now is not None and stamp_ns > now + self._far_ns
        if last is None and now is not None and stamp_ns < now - self._far_ns:
            behind = True  # a stream's first message far behind the others
        if behind or ahead:
            if self._in_flight(stamp_ns):
                return Verdict("time_jump", f"{stream}: stamp {stamp_ns * 1e-9:.3f} s is of the time before the "
                                            "restart, handed over after it (a busy reader): lost to the restart")
            error = self._off_timeline_error(sensor, stream, stamp_ns, last if behind else None)
            restart, taken = self._candidate(Held(sensor, stream, stamp_ns, message))
            if restart is not None and taken:
                return Verdict(restart=restart)  # a message of the new timeline, not held: on time
            return Verdict("bad_stamp", error, restart)
        if any(self._spoke.values()):
            if self._candidates[key]:  # a stream back from the new timeline: what was building up is not a restart
                self._close_episode()
            else:  # a stream yet to move: its messages may still be in flight (a busy reader), or it stays
                first_ns = self._lagging[key][0] if key in self._lagging else stamp_ns
                if stamp_ns - first_ns > self._far_ns:  # it stays on the old timeline: not a restart
                    self._close_episode()
                else:
                    self._lagging[key] = (first_ns, max(c[-1] for c in self._candidates.values() if c))
        if stream == "depth":
            verdict = self._depth_order(key, stamp_ns, last)
        else:
            self._last_ns[key] = stamp_ns if last is None else max(last, stamp_ns)
            verdict = Verdict()
        self._taken += verdict.reason is None
        return verdict

    def _depth_order(self, key: tuple[str, str], stamp_ns: int, last: int | None) -> Verdict:
        """A depth stamp on its stream's timeline must be new and move forward. One that falls between
        the two newest is taken, and the stream's time goes back to it: the newest was stamped ahead
        of its place (a glitching driver) or two frames crossed, and the frames after it would
        otherwise all be out of order until the stream caught up with it. Before a second newest, any
        older one is between (the stream's first two frames crossed)."""
        recent, previous = self._recent_depth_ns[key], self._previous_depth_ns.get(key)
        if stamp_ns in recent:
            return Verdict("duplicate")
        if last is not None and stamp_ns < last and previous is not None and stamp_ns < previous:
            return Verdict("out_of_order")
        if last is not None and stamp_ns > last:
            self._previous_depth_ns[key] = last
        recent.append(stamp_ns)
        self._last_ns[key] = stamp_ns
        return Verdict()

    def _off_timeline_error(self, sensor: str, stream: str, stamp_ns: int, own_last_ns: int | None) -> str:
        """What a bad_stamp's error says: off the stream's own timeline (`own_last_ns`: it is behind that),
        or off the other streams' time while its sensor has no time of its own or keeps to it (its clock
        differs from theirs)."""
        now = self.now_ns()
        assert now is not None  # off needs a timeline
        t = f"{stream}: stamp {stamp_ns * 1e-9:.3f} s"
        own_ns = self.sensor_now_ns(sensor)
        if own_last_ns is None and (own_ns is None or abs(stamp_ns - own_ns) <= self._far_ns):
            return (f"{t} is {abs(stamp_ns - now) * 1e-9:.3f} s {'behind' if stamp_ns < now else 'ahead of'} the "
                    f"other sensors' time ({now * 1e-9:.3f} s): {sensor}'s clock differs from theirs, or its driver "
                    f"restarted on another clock; give every sensor one clock (e.g. PTP or chrony): {sensor}'s "
                    "messages are dropped until its stamps agree with the others'")
        ref = own_last_ns if own_last_ns is not None else now
        return (f"{t} is {abs(stamp_ns - ref) * 1e-9:.3f} s {'behind' if stamp_ns < ref else 'ahead of'} the "
                f"stream's timeline; check the driver's clock (a restart is recognised once every stream continues on "
                f"the new timeline; if only {sensor}'s moved, its driver restarted on another clock, and its messages "
                "are dropped until its stamps agree with the other sensors' again)")

    def _in_flight(self, stamp_ns: int) -> bool:
        """Whether an off-timeline stamp is a message of the time before the latest restart that was
        still in flight: near the old timeline's newest stamp, while the new timeline has gone on for
        less than time_jump_s. Such a message is the restart's loss (`time_jump`), not a bad stamp, and
        no candidate: a stamp far from both timelines (an unset stamp 0) stays a bad_stamp."""
        if self._old_time is None:
            return False
        old_ns, restarted_ns = self._old_time
        now = self.now_ns()
        return abs(stamp_ns - old_ns) <= self._far_ns and now is not None and now - restarted_ns <= self._far_ns

    def pending(self) -> bool:
        """Whether off-timeline stamps wait to be confirmed as a restart (or found to be strays)."""
        return any(self._candidates.values())

    def restart(self, to_ns: int | None) -> Restart:
        """Time restarted at `to_ns` (None: unknown), known from outside (the /clock went back): every
        timeline is forgotten and the streams start again from `to_ns`, so that messages of the old
        time still in flight are off it. Messages of the new time that came before the news (a
        pose callback ran before the /clock's), held as candidates of a new timeline, are handed
        back with the restart: the streams go on from them."""
        near: dict[tuple[str, str], list[int]] = {}
        held: list[Held] = []
        lost: dict[tuple[str, str], int] = {}
        for key, candidates in self._candidates.items():
            stamps = [t for t in candidates if to_ns is not None and abs(t - to_ns) <= self._far_ns]
            if stamps:
                assert to_ns is not None
                near[key] = stamps
                kept = [m for m in self._held[key] if abs(m.stamp_ns - to_ns) <= self._far_ns]
                held += kept
                if len(stamps) > len(kept):
                    lost[key] = len(stamps) - len(kept)
        restart = self._move({key: stamps[-1] for key, stamps in near.items()}, Restart(
            to_ns if to_ns is not None else 0, self.now_ns(), tuple(sorted(held, key=lambda m: m.stamp_ns)), lost))
        self._anchor_ns = to_ns
        self._take_depth_stamps(near)
        return restart

    def _candidate(self, message: Held) -> tuple[Restart | None, bool]:
        """Remember an off-timeline stamp; move to the new timeline when every stream is on it.
        Returns the restart (or None) and whether the message was taken as a candidate (not a copy of
        one); with a restart, such a message is not among the held ones: the caller takes it."""
        key, stamp_ns = (message.sensor, message.stream), message.stamp_ns
        self._spoke[key] = True
        candidates = self._candidates[key]
        if candidates and abs(stamp_ns - candidates[-1]) <= self._far_ns:
            # on the new timeline; one older than the newest came late (two threads take a subscription's
            # messages: its callback, and the depth images' before them): kept in stamp order, each once
            place = bisect.bisect_left(candidates, stamp_ns)
            taken = place == len(candidates) or candidates[place] != stamp_ns
            if taken:
                candidates.insert(place, stamp_ns)
                self._held[key].append(message)
        else:  # not consistent with what came before: start over
            taken = True
            self._candidates[key] = [stamp_ns]
            self._held[key].clear()
            self._held[key].append(message)
        lists = {k: self._candidates[k] for k, spoke in self._spoke.items() if spoke}
        if any(len(c) < self._confirm_msgs for c in lists.values()):
            return None, taken
        firsts, lasts = [c[0] for c in lists.values()], [c[-1] for c in lists.values()]
        if max(lasts) - min(firsts) < self._confirm_ns or max(lasts) - min(lasts) > self._far_ns:
            return None, taken
        # a stream that spoke on the old timeline meanwhile must have moved too, unless the new timeline went
        # on for longer than time_jump_s since it last spoke (it stopped: a restart it is not part of)
        if any(k not in lists and max(lasts) - heard_ns <= self._far_ns for k, (_, heard_ns) in self._lagging.items()):
            return None, taken
        if taken:
            self._held[key].pop()  # the message being checked, held last: its caller takes it
        lost = {k: len(c) - len(self._held[k]) - (k == key and taken) for k, c in lists.items()}
        held = sorted((m for k in lists for m in self._held[k]), key=lambda m: m.stamp_ns)
        restart = Restart(min(firsts), self.now_ns(), tuple(held), {k: n for k, n in lost.items() if n},
                          stray_start=self._taken < self._confirm_msgs)
        # ahead (every stream paused, one clock): a stream yet to speak keeps its timeline, so that its first
        # messages are judged by it, not by how far a burst took the streams that confirmed the restart
        self._move({k: c[-1] for k, c in lists.items()}, restart, keep_silent=not restart.went_back)
        self._take_depth_stamps(lists)
        return restart, taken

    def _take_depth_stamps(self, candidates: Mapping[tuple[str, str], list[int]]) -> None:
        """The new timeline's depth stamps are taken: a copy that comes again is a duplicate, and an
        older one out of order."""
        for k, stamps in candidates.items():
            if k[1] == "depth":
                self._recent_depth_ns[k].extend(stamps)
                if len(stamps) > 1:
                    self._previous_depth_ns[k] = stamps[-2]

    def _move(self, timelines: dict[tuple[str, str], int], restart: Restart, *, keep_silent: bool = False
              ) -> Restart:
        """Every stream onto the new timeline (its newest candidate, or none yet); `keep_silent`: a stream
        without candidates keeps its own."""
        for key in self._last_ns:
            if key in timelines or not keep_silent:
                self._last_ns[key] = timelines.get(key)
        for recent in self._recent_depth_ns.values():
            recent.clear()
        self._previous_depth_ns.clear()
        self._anchor_ns = None
        self._taken = 0
        self._close_episode()
        # the new timeline's newest stamp, or (/clock) where it restarted
        new_ns = max(timelines.values(), default=restart.to_ns)
        self._old_time = None if restart.from_ns is None else (restart.from_ns, new_ns)
        return restart

    def _close_episode(self) -> None:
        for key in self._candidates:
            self._candidates[key], self._spoke[key] = [], False
            self._held[key].clear()
        self._lagging.clear()


@dataclass(frozen=True)
class Gap:
    """Images missing from a stream between two consecutive stamps (`StreamGaps`)."""

    from_ns: int
    to_ns: int
    period_ns: int  # the stream's period before it
    missing: int  # images the gap would have held
    # > 0: this gap ended a run of gaps of about this length, which is the stream's period from now on
    new_period_ns: int = 0


class StreamGaps:
    """Images missing from a stream of regular stamps (a depth camera's frames): an interval of
    `_GAP_PERIODS` or more of the stream's period (the median of its recent intervals) held
    round(interval / period) - 1 images that never came on time (lost before they reached the
    node: a burst overflowing a subscription's queue, a recorder that dropped them; or the driver
    skipped them). `_RATE_CHANGE_GAPS` such intervals in a row of about the same length, none of them
    filled by an image that came late, are a stream whose rate went down (a driver reconfigured, or
    images lost steadily): their length is its period from then on, so that it is not found to lose
    images for as long as it runs (the gaps up to then stay counted: stamps cannot tell the two apart).
    Stamps only: the caller feeds the stamps it took on time, in order."""

    def __init__(self) -> None:
        self._last_ns: int | None = None
        self._intervals: deque[int] = deque(maxlen=_PERIOD_INTERVALS)
        # the lengths of the gaps in a row since the last regular interval or late image
        self._long: deque[int] = deque(maxlen=_RATE_CHANGE_GAPS)
        # the latest gaps the caller counted (`count`), and the stamps that came late into each (`came_late`)
        self._counted: deque[tuple[Gap, set[int]]] = deque(maxlen=_COUNTED_GAPS)

    def restart(self) -> None:
        """Time restarted, or every stream paused: the next stamp starts anew (the period stays)."""
        self._last_ns = None
        self._counted.clear()
        self._long.clear()

    def count(self, gap: Gap) -> None:
        """The caller counted this gap's images as missing: one that still comes is taken back (`came_late`)."""
        self._counted.append((gap, set()))

    def came_late(self, stamp_ns: int) -> bool:
        """Whether a stamp older than the newest lies in a gap counted lately, one of its images that came
        late (frames logged or delivered out of order), once each: it is not missing, whether the caller
        took it or dropped it."""
        if self._last_ns is not None and stamp_ns < self._last_ns:
            self._long.clear()  # images in the wrong order: the gaps are no steady new rate
        for gap, late in self._counted:
            if gap.from_ns < stamp_ns < gap.to_ns and stamp_ns not in late and len(late) < gap.missing:
                late.add(stamp_ns)
                return True
        return False

    def add(self, stamp_ns: int) -> Gap | None:
        """The gap before this stamp, if it ends one; a stamp older than the newest is ignored (the
        caller tells `came_late`)."""
        last = self._last_ns
        if last is not None and stamp_ns <= last:
            return None
        self._last_ns = stamp_ns
        if last is None:
            return None
        interval = stamp_ns - last
        if len(self._intervals) >= _MIN_INTERVALS:
            period_ns = int(statistics.median(self._intervals))
            if interval >= _GAP_PERIODS * period_ns:  # kept out of the period
                self._long.append(interval)
                new_period_ns = 0
                if len(self._long) == _RATE_CHANGE_GAPS and max(self._long) <= _STEADY_RATIO * min(self._long):
                    self._intervals.clear()
                    self._intervals.extend(self._long)
                    self._long.clear()
                    new_period_ns = int(statistics.median(self._intervals))
                return Gap(last, stamp_ns, period_ns, round(interval / period_ns) - 1, new_period_ns)
        self._long.clear()
        self._intervals.append(interval)
        return None


class ClockTimeline:
    """/clock under use_sim_time: a step back by more than the jump (time_jump_s) is a restart once the
    next /clock goes on from there (a bag looping); one that the next /clock leaves again for the old
    time was a stray message (a second /clock publisher), which restarts nothing. Not thread-safe: its
    owner (the node's /clock watch) calls it under a lock."""

    def __init__(self) -> None:
        self.last_ns: int | None = None  # the newest /clock of the current timeline
        self._back_ns: int | None = None  # a /clock that went back, until the next one tells which it was

    def observe(self, now_ns: int, jump_ns: int) -> tuple[str, int, int] | None:
        """("restart", from_ns, to_ns) when this /clock confirms a restart to to_ns, ("stray", from_ns,
        back_ns) when it shows that the one before (back_ns) was a stray, else None."""
        last, back = self.last_ns, self._back_ns
        self._back_ns = None
        if last is not None and now_ns < last - jump_ns:
            if back is None:  # it went back: the next /clock tells
                self._back_ns = now_ns
                return None
            self.last_ns = now_ns
            return "restart", last, now_ns
        self.last_ns = now_ns
        return None if back is None else ("stray", last if last is not None else now_ns, back)

    def reset(self) -> None:
        """Forget the timeline (the /clock seen before the watch stopped is no reference)."""
        self.last_ns = self._back_ns = None
