"""Publish a rosbag2 bag's messages with rclpy, paced by bag time (``bearing_loc bag play``).

For machines without the ROS 2 CLI's rosbag2: raw CDR bytes are published on publishers with
each topic's recorded QoS, with a ``/clock`` like ``ros2 bag play --clock``.
"""

import math
import signal
import sys
import threading
import time

from .cli import InputError

NS_PER_S = 1_000_000_000


def _import_msg_class(msgtype):
    import importlib
    pkg, kind, name = msgtype.split('/')
    try:
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ImportError, AttributeError):
        raise InputError(f'bag: message type {msgtype!r} is not installed') from None


def _qos_from_dict(q):
    """rclpy QoSProfile of a recorded offered profile (metadata v9 dict)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    depth = max(int(q.get('depth', 10) or 10), 1)
    rel = (ReliabilityPolicy.BEST_EFFORT if q.get('reliability') == 'best_effort'
           else ReliabilityPolicy.RELIABLE)
    dur = (DurabilityPolicy.TRANSIENT_LOCAL if q.get('durability') == 'transient_local'
           else DurabilityPolicy.VOLATILE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel,
                      durability=dur)


def play_bag(path, rate=1.0, loop=False, clock_rate=0.0, delay=0.0, wait_for_subscribers=0.0,
             topics=None, quiet=False, log=None):
    """Publish the messages of bag ``path`` paced by bag time / ``rate`` (rclpy node).

    Raw CDR bytes are published as they are (``Publisher.publish(bytes)``), on publishers with
    each topic's recorded reliability/durability/depth (rosbag2 player's QoS adaptation).
    ``/clock``: with ``clock_rate`` > 0, a rosgraph_msgs/Clock with the playback time
    t0 + (wall − wall0) · rate is published at ``clock_rate`` Hz wall and the bag's own
    /clock is skipped; otherwise the bag's /clock messages are replayed, or, if it has none,
    a clock is generated at 100 Hz. Messages of one bag instant go out before its clock tick.
    Returns 0; Ctrl-C stops cleanly.
    """
    import rclpy
    from rclpy.duration import Duration
    from rclpy.executors import ExternalShutdownException
    from rosgraph_msgs.msg import Clock
    from . import bagio
    if not (rate > 0 and math.isfinite(rate)):
        raise InputError(f'rate: must be > 0 (got {rate})')
    if clock_rate < 0 or not math.isfinite(clock_rate):
        raise InputError(f'clock_rate: must be >= 0 (got {clock_rate})')
    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    with bagio.BagReader(path) as reader:
        info = reader.topics
    if topics:
        missing = [t for t in topics if t not in info]
        if missing:
            raise InputError(f'topics: not in the bag: {", ".join(missing)}')
        info = {k: v for k, v in info.items() if k in topics}
    has_clock = bagio.CLOCK_TOPIC in info
    generate = clock_rate > 0 or not has_clock
    gen_hz = clock_rate if clock_rate > 0 else 100.0
    from rclpy.signals import SignalHandlerOptions
    # No rclpy signal handler: with it, Ctrl-C shuts the context down and the next
    # publish raises RCLError (a traceback, exit 1). Python's own handler raises
    # KeyboardInterrupt, caught below; installed explicitly because a shell starts
    # background jobs with SIGINT ignored.
    old_sigint = None
    if threading.current_thread() is threading.main_thread():
        old_sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    rclpy.init(args=['--ros-args'], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bag_player')
    try:
        pubs = {}
        for name, t in info.items():
            if name == bagio.CLOCK_TOPIC and generate:
                continue
            pubs[name] = node.create_publisher(_import_msg_class(t.msgtype), name,
                                               _qos_from_dict(t.qos[0] if t.qos else {}))
        clock_pub = node.create_publisher(Clock, bagio.CLOCK_TOPIC,
                                          _qos_from_dict(bagio.CLOCK_QOS)) if generate else None
        if wait_for_subscribers > 0:
            deadline = time.monotonic() + wait_for_subscribers
            while time.monotonic() < deadline:
                if all(p.get_subscription_count() > 0 for p in pubs.values()):
                    break
                time.sleep(0.02)
            lonely = [n for n, p in pubs.items() if p.get_subscription_count() == 0]
            if lonely and not quiet:
                log(f'bag play: no subscriber yet on {", ".join(sorted(lonely))}')
        if delay > 0:
            time.sleep(delay)
        period_ns = int(NS_PER_S / gen_hz)
        while True:
            n = _play_once(path, pubs, clock_pub, rate, period_ns, set(info), quiet, log)
            if not loop or not rclpy.ok():
                break
        for p in pubs.values():
            p.wait_for_all_acked(Duration(seconds=2.0))
        if not quiet:
            log(f'bag play: done ({n} messages per pass)')
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        if old_sigint is not None:
            signal.signal(signal.SIGINT, old_sigint)
    return 0


def _play_once(path, pubs, clock_pub, rate, period_ns, topics, quiet, log):
    """One pass over the bag; returns the number of messages published."""
    from rosgraph_msgs.msg import Clock
    from . import bagio
    from .ros_conversions import ns_to_time

    def clock_at(t_ns):
        if clock_pub is not None:
            clock_pub.publish(Clock(clock=ns_to_time(max(0, t_ns))))

    count = 0
    with bagio.BagReader(path) as reader:
        t0 = reader.start_time_ns
        wall0 = time.monotonic_ns()
        next_tick = wall0
        clock_at(t0)
        held_clock = []   # bag /clock messages of the current instant: sent after its data
        current = None
        for m in reader.messages(topics=topics):
            if m.log_time_ns != current:
                for raw in held_clock:
                    pubs[bagio.CLOCK_TOPIC].publish(raw)
                held_clock = []
                current = m.log_time_ns
            due = wall0 + int((m.log_time_ns - t0) / rate)
            while True:
                now = time.monotonic_ns()
                if clock_pub is not None and next_tick <= min(now, due):
                    clock_at(min(t0 + int((next_tick - wall0) * rate), m.log_time_ns))
                    next_tick += period_ns
                    continue
                if now >= due:
                    break
                wake = due if clock_pub is None else min(due, next_tick)
                time.sleep(max(0.0, (wake - now) / NS_PER_S))
            pub = pubs.get(m.topic)
            if pub is None:
                continue
            if m.topic == bagio.CLOCK_TOPIC:
                held_clock.append(m.raw)
            else:
                pub.publish(m.raw)
            count += 1
        for raw in held_clock:
            pubs[bagio.CLOCK_TOPIC].publish(raw)
        if current is not None:
            clock_at(current)
    return count
