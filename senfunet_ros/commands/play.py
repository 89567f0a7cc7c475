"""`senfunet play BAG`: publish a recording on its topics with /clock, paced in real time x rate."""
from __future__ import annotations

import argparse
import sys
import time

HELP = "publish a recorded bag on its topics with /clock (for nodes using use_sim_time), at a chosen rate"

_CLOCK_PERIOD_S = 0.01  # /clock keeps ticking at this (wall) period while waiting for the next message
# a recorded /clock this long (log time) behind the other messages, and 5 of its own intervals, stopped
_CLOCK_SILENT_NS = 500_000_000
_SKIPPED_GAP_NS = 86_400 * 10**9  # log times a day apart: a recorder's clock error (log time 0), no pause to wait
# Our writers matching a subscriber (what --wait-subscribers sees) does not mean that its reader has
# matched our writers yet, and a best-effort reader drops whatever arrives before it has. The other
# side follows soon, later on a loaded machine (the streamed node test lost its first poses without
# a wait); so once every topic has a subscriber, wait this, with a margin for a loaded machine.
_MATCH_SETTLE_S = 1.0

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", metavar="BAG", help="rosbag2 folder (mcap or sqlite3) or a .mcap file")
    parser.add_argument("--rate", type=float, default=1.0, metavar="R", help="playback speed factor (default 1.0)")
    parser.add_argument("--loop", action="store_true", help="start over when the bag ends (until Ctrl-C)")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="publish only these topics")
    parser.add_argument("--no-clock", action="store_true",
                        help="do not publish /clock (neither play's own nor a recorded one)")
    parser.add_argument("--wait-subscribers", type=float, default=0.0, metavar="S",
                        help="wait up to S seconds until every topic has a subscriber before starting, then "
                        f"{_MATCH_SETTLE_S:g} s more for their side of discovery (default 0: no wait)")
    parser.add_argument("--delay", type=float, default=0.0, metavar="S", help="sleep S seconds before publishing")
    parser.add_argument("--quiet", action="store_true", help="print only errors")


def _error(text: str) -> int:
    print(f"senfunet play: {text}", file=sys.stderr)
    return 2


def _stop(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    import signal

    from senfunet_ros.bagio import BagError, open_bag

    # a stop while the bag is opened (a copy or decompression, seconds on a large bag; rclpy's handler
    # comes later) or played (SIGHUP: the terminal closed) ends play cleanly: its temporary files go
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _stop)
    if not args.rate > 0:
        return _error(f"--rate must be > 0, got {args.rate}")
    try:
        reader = open_bag(args.bag)
    except BagError as err:
        return _error(str(err))
    except KeyboardInterrupt:
        if not args.quiet:
            print("senfunet play: stopped", file=sys.stderr)
        return 0
    with reader:
        try:
            return _play(reader, args)
        except KeyboardInterrupt:
            # one Ctrl-C arrives twice: rclpy's handler shuts the context down (a publish raises) and
            # chains to Python's, whose KeyboardInterrupt can come while _play handles the first
            if not args.quiet:
                print("senfunet play: stopped", file=sys.stderr)
            return 0


def _play(reader, args: argparse.Namespace) -> int:  # noqa: ANN001 - BagReader, imported lazily
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from senfunet_ros.bagio import BagError, absolute_topic

    say = (lambda text: None) if args.quiet else (lambda text: print(f"senfunet play: {text}", file=sys.stderr))
    if reader.note:
        say(f"note: {reader.note}")
    try:
        classes = _message_classes(reader, args.topics, say)
    except BagError as err:
        return _error(str(err))

    from senfunet_ros.dds import shut_down_rclpy, use_large_shm_profile

    use_large_shm_profile()  # before the participant exists: Fast DDS reads it then
    rclpy.init(args=None)
    node = None
    try:
        node = rclpy.create_node("senfunet_play", start_parameter_services=False)
        # Reliable matches reliable and best-effort subscribers; volatile like a live driver, but
        # transient-local where the recording's publisher was (a latched /tf_static: its subscribers
        # ask for transient-local, which a volatile writer does not match)
        topics = reader.topics
        publishers = {}
        for t, cls in list(classes.items()):
            if _is_clock(t) and args.no_clock:  # a recorded clock too
                del classes[t]
                continue
            latched = topics[t].latched or absolute_topic(t) == "/tf_static"
            try:
                publishers[t] = node.create_publisher(cls, t, QoSProfile(
                    history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE))
            except InvalidTopicNameException as err:  # a name another middleware allowed ('color-raw')
                del classes[t]
                reason = str(err).strip().splitlines()[0]
                say(f"{t} is no valid ROS 2 topic name ({reason}): not published; rename it (ros2 bag convert, "
                    "or rosbags' tools) to play it")
        for topic in classes:
            if len(topics[topic].types) > 1:
                others = ", ".join(f"{n} {t}" for t, n in topics[topic].types.items() if t != topics[topic].msgtype)
                say(f"{topic} was recorded with several types: playing its {topics[topic].msgtype} messages, "
                    f"leaving out {others}")
        clock_pub = None
        if any(map(_is_clock, publishers)) and not args.no_clock:  # a second clock would make time jump to and fro
            say("the bag has /clock (a simulation's recorded clock): playing it, and no /clock of play's own")
        elif not args.no_clock:
            from rosgraph_msgs.msg import Clock

            clock_pub = node.create_publisher(Clock, "/clock",
                                              QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
            clock_msg = Clock()

        def publish_clock(stamp_ns: int) -> None:
            if clock_pub is not None:
                clock_msg.clock.sec, clock_msg.clock.nanosec = divmod(int(stamp_ns), 1_000_000_000)
                clock_pub.publish(clock_msg)

        if args.wait_subscribers > 0:
            _wait_for_subscribers(publishers, args.wait_subscribers, say)
        if args.delay > 0:
            time.sleep(args.delay)

        say(f"playing {reader.path} ({reader.storage}, {reader.duration_s:.1f} s, {len(publishers)} topics) "
            f"at rate {args.rate:g}{' in a loop' if args.loop else ''}")
        total, passes, broken = 0, 0, None
        while True:
            gaps: list[tuple[int, int]] = []
            clock_stops: list[tuple[int, int]] = []
            published, broken, not_cdr = _play_once(reader, publishers, publish_clock, rate=args.rate,
                                                    types={t: topics[t].msgtype for t in publishers}, gaps=gaps,
                                                    clock_stops=clock_stops)
            total += published
            passes += 1
            if passes == 1:
                for note in reader.read_notes():
                    say(f"note: {note}")
                for before_ns, after_ns in gaps:
                    say(f"the log times jump from {before_ns * 1e-9:.3f} s to {after_ns * 1e-9:.3f} s (a recorder's "
                        "clock error, such as messages logged at 0?): played without waiting for the gap")
                for last_clock_ns, log_ns in clock_stops:
                    say(f"the recorded clock stopped at log time {last_clock_ns * 1e-9:.3f} s while the other "
                        f"topics went on (to {log_ns * 1e-9:.3f} s at least): nodes with use_sim_time see their time "
                        "stand still from there; play with --no-clock (and those nodes without use_sim_time), or "
                        "record the clock to the end")
                for topic, n in sorted(not_cdr.items()):
                    say(f"{n} message(s) on {topic} are not ROS 2 serialised messages (CDR): ROS 1 or JSON data? "
                        "They were not published; convert the bag (rosbags-convert) or record it with ros2 bag")
            if broken or not args.loop or total == 0:
                break
        # Reliable writers keep what slow readers have not acknowledged; hand it over before exiting.
        from rclpy.duration import Duration

        ack_deadline = time.monotonic() + 5.0
        for publisher in publishers.values():
            publisher.wait_for_all_acked(Duration(seconds=max(0.0, ack_deadline - time.monotonic())))
        say(f"published {total} messages in {passes} pass(es)")
        if broken:
            return _error(broken)
        return 0 if total else _error("nothing in the bag could be published (see above)")
    except (KeyboardInterrupt, ExternalShutdownException):
        say("stopped")
        return 0  # stopping is how a looping play ends: not an error
    except Exception:  # the stop raced a publish: the context went away under it
        if rclpy.ok():
            raise
        say("stopped")
        return 0
    finally:
        if node is not None:
            node.destroy_node()
        shut_down_rclpy()


def _is_clock(topic: str) -> bool:
    """/clock, or `clock` as a recorder may name it (`bagio.absolute_topic`)."""
    from senfunet_ros.bagio import absolute_topic

    return absolute_topic(topic) == "/clock"


def _message_classes(reader, topics: list[str] | None, say) -> dict[str, type]:  # noqa: ANN001
    """Topic -> message class of the topics to play (all, or `topics`); topics whose type is not
    installed here are skipped with a note. BagError when a topic is missing or none can be played."""
    from senfunet_ros.bagio import BagError, absolute_topic, message_class

    infos = reader.topics
    if topics:  # 'tof/pose' is '/tof/pose', as everywhere else: the bag's spellings of each are played
        chosen = {absolute_topic(t) for t in topics}
        missing = sorted(chosen - {absolute_topic(t) for t in infos})
        if missing:
            raise BagError(f"{reader.path}: no topic {', '.join(missing)}; the bag has {', '.join(sorted(infos))}")
        # a recorded clock is the time of the topics chosen (a simulation's stamps): it goes with them
        infos = {t: info for t, info in infos.items() if absolute_topic(t) in chosen or _is_clock(t)}
    classes: dict[str, type] = {}
    unknown: dict[str, str] = {}
    for topic, info in sorted(infos.items()):
        try:
            classes[topic] = message_class(info.msgtype)
        except BagError:
            unknown[topic] = info.msgtype
    types = ", ".join(sorted(set(unknown.values())))
    if not classes:
        raise BagError(f"{reader.path}: none of its topics has a message type installed here ({types}); "
                       "install their packages (pip install ros-jazzy-<package>)")
    if unknown:
        say(f"skipping {', '.join(unknown)}: message types not installed here ({types})")
    return classes


def _wait_for_subscribers(publishers: dict, timeout_s: float, say) -> None:  # noqa: ANN001
    """Up to timeout_s for every topic to have a subscriber (then a moment for their side of discovery)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if all(p.get_subscription_count() > 0 for p in publishers.values()):
            break
        time.sleep(0.05)
    lonely = [t for t, p in publishers.items() if p.get_subscription_count() == 0]
    if lonely:
        say(f"no subscriber yet on {', '.join(lonely)}; playing anyway")
    else:
        time.sleep(_MATCH_SETTLE_S)  # the subscribers' side of discovery


def _play_once(reader, publishers: dict, publish_clock, *, rate: float,  # noqa: ANN001
               types: dict[str, str], gaps: list[tuple[int, int]], clock_stops: list[tuple[int, int]]
               ) -> tuple[int, str | None, dict[str, int]]:
    """One pass through the bag at `rate`, ticking /clock while it waits: the messages published
    (of each topic, those of its type in `types`), where the bag broke (None if it did not), and per
    topic the messages left out because they are not CDR (a subscriber could not read them). A gap
    of log times longer than _SKIPPED_GAP_NS is not waited through; `gaps` gets its ends. A recorded
    clock silent for _CLOCK_SILENT_NS (and 5 of its intervals) while the other topics went on for 5 of
    its intervals gets (its last log time, the other topics' last then) in `clock_stops`, once.
    ExternalShutdownException when Ctrl-C or SIGTERM shut rclpy down."""
    from senfunet_ros.bagio import is_cdr, normalize_msgtype

    import rclpy
    from rclpy.executors import ExternalShutdownException

    from senfunet_ros.bagio import BagBrokenError

    start_ns = reader.start_ns
    wall0 = time.monotonic()
    publish_clock(start_ns)
    published = 0
    not_cdr: dict[str, int] = {}
    last_ns = start_ns
    last_clock_ns, clock_interval_ns = None, 0  # log time of the recorded clock's last message, its last interval
    # log times of the other topics' first and last messages since the clock fell silent: a pause of every
    # topic (the clock resuming with them) is no stop, other topics going on while it is silent are
    silent_from_ns, silent_to_ns = None, None

    def silence_ends() -> None:
        if (silent_from_ns is not None and silent_to_ns is not None and not clock_stops
                and silent_to_ns - silent_from_ns >= 5 * clock_interval_ns):
            clock_stops.append((last_clock_ns, silent_to_ns))
    try:
        for msg in reader.messages(publishers.keys()):
            if normalize_msgtype(msg.msgtype) != types[msg.topic]:
                continue
            if not is_cdr(msg.data):
                not_cdr[msg.topic] = not_cdr.get(msg.topic, 0) + 1
                continue
            if msg.log_time_ns - last_ns > _SKIPPED_GAP_NS:  # a clock error (log times of 0), not a pause: skipped
                gaps.append((last_ns, msg.log_time_ns))
                start_ns += msg.log_time_ns - last_ns
            last_ns = max(last_ns, msg.log_time_ns)
            if _is_clock(msg.topic):
                silence_ends()
                silent_from_ns = silent_to_ns = None
                clock_interval_ns = 0 if last_clock_ns is None else msg.log_time_ns - last_clock_ns
                last_clock_ns = msg.log_time_ns
            elif last_clock_ns is not None and msg.log_time_ns - last_clock_ns > max(_CLOCK_SILENT_NS,
                                                                                   5 * clock_interval_ns):
                silent_from_ns = msg.log_time_ns if silent_from_ns is None else silent_from_ns
                silent_to_ns = msg.log_time_ns
            due = wall0 + (msg.log_time_ns - start_ns) * 1e-9 / rate
            while True:  # sleep until due, ticking /clock meanwhile
                wait = due - time.monotonic()
                if wait <= 0:
                    break
                time.sleep(min(wait, _CLOCK_PERIOD_S))
                if wait > _CLOCK_PERIOD_S:
                    now_ns = start_ns + int((time.monotonic() - wall0) * rate * 1e9)
                    publish_clock(min(now_ns, msg.log_time_ns))
            if not rclpy.ok():  # Ctrl-C / SIGTERM: rclpy's handler shut the context down
                raise ExternalShutdownException()
            publish_clock(msg.log_time_ns)
            publishers[msg.topic].publish(msg.data)  # raw CDR straight from the bag
            published += 1
    except BagBrokenError as err:
        silence_ends()
        return published, str(err), not_cdr
    silence_ends()
    return published, None, not_cdr
