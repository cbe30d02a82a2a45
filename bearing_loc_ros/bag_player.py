"""Publish a rosbag2 bag's messages with rclpy, paced by bag time (``bearing_loc bag play``).

For machines without the ROS 2 CLI's rosbag2: raw CDR bytes are published on publishers with
each topic's recorded QoS, with a ``/clock`` like ``ros2 bag play --clock``.
"""

import signal
import sys
import threading
import time

from .cli import InputError

NS_PER_S = 1_000_000_000
#: Default bound (s) of the wait for matched subscribers before playing.
DEFAULT_WAIT_S = 5.0
#: The ROS graph must be unchanged this long (s) before playing (subscriber discovery).
SETTLE_S = 1.0
#: Upper bound (s) of ``delay`` and ``wait_for_subscribers`` (one day).
MAX_WAIT_S = 86400.0


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


def play_bag(path, rate=1.0, loop=False, clock_rate=0.0, delay=0.0,
             wait_for_subscribers=DEFAULT_WAIT_S, topics=None, quiet=False, log=None):
    """Publish the messages of bag ``path`` paced by bag time / ``rate`` (rclpy node).

    Raw CDR bytes are published as they are (``Publisher.publish(bytes)``), on publishers with
    each topic's recorded reliability/durability/depth (rosbag2 player's QoS adaptation).
    ``/clock``: with ``clock_rate`` > 0, a rosgraph_msgs/Clock with the playback time
    t0 + (wall − wall0) · rate is published at ``clock_rate`` Hz wall and the bag's own
    /clock is skipped; otherwise the bag's /clock messages are replayed, or, if it has none,
    a clock is generated at 100 Hz. Messages of one bag instant go out before its clock tick,
    except on the passes of a ``loop`` after the first: there the clock jumps back to the
    bag's first /clock message before the first instant's data go out.
    Topics whose message type is not installed are skipped with a warning (as rosbag2 does),
    and so are single messages that cannot be published (:func:`_play_once`: an unreadable
    bag /clock message, one the middleware refuses), counted in a warning after the first
    pass. Before playing, waits up to ``wait_for_subscribers`` s (see :func:`wait_for_subscribers`;
    0: no wait). ``delay`` and ``wait_for_subscribers`` are within [0, MAX_WAIT_S] s.
    Returns 0; Ctrl-C stops cleanly.
    """
    import rclpy
    from rclpy.duration import Duration
    from rclpy.executors import ExternalShutdownException
    from rosgraph_msgs.msg import Clock
    from . import bagio
    if not 1e-6 <= rate <= 1e6:        # (a wait of bag time / 1e-300 overflows)
        raise InputError(f'rate: must be in [1e-06, 1e+06] (got {rate})')
    if not 0 <= clock_rate <= 1e4:
        raise InputError(f'clock_rate: must be in [0, 1e4] Hz (got {clock_rate})')
    for name, value in (('delay', delay), ('wait_for_subscribers', wait_for_subscribers)):
        if not 0 <= value <= MAX_WAIT_S:        # NaN too
            raise InputError(f'{name}: must be within [0, {MAX_WAIT_S:g}] s (got {value})')
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
    classes, skipped = {}, []
    for name, t in info.items():
        if name == bagio.CLOCK_TOPIC and generate:
            continue
        try:
            classes[name] = _import_msg_class(t.msgtype)
        except InputError:
            skipped.append(f'{name} ({t.msgtype})')
    if skipped:
        log('bag play: warning: message type not installed, not played: ' + ', '.join(skipped))
    if not classes:
        raise InputError(f'bag: {path} has no topic of an installed message type')
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
        pubs = {name: node.create_publisher(cls, name, _qos_from_dict(
                    info[name].qos[0] if info[name].qos else {}))
                for name, cls in classes.items()}
        clock_pub = node.create_publisher(Clock, bagio.CLOCK_TOPIC,
                                          _qos_from_dict(bagio.CLOCK_QOS)) if generate else None
        if wait_for_subscribers > 0:
            waited = dict(pubs, **({bagio.CLOCK_TOPIC: clock_pub} if clock_pub else {}))
            wait_for_subscribers_of(node, waited, wait_for_subscribers, quiet, log)
        if delay > 0:
            time.sleep(delay)
        period_ns = int(NS_PER_S / gen_hz)
        again = False
        while True:
            n = _play_once(path, pubs, clock_pub, rate, period_ns, set(classes) | (
                {bagio.CLOCK_TOPIC} & set(info)), quiet, log, again)
            if not loop or not rclpy.ok():
                break
            again = True
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


def wait_for_subscribers_of(node, pubs, timeout, quiet=False, log=print):
    """Wait until every topic of ``pubs`` (name -> publisher) that has a subscriber is matched.

    A topic counts as waited for when the ROS graph shows a subscription on it
    (``node.count_subscribers``) that is not yet matched with our publisher
    (``get_subscription_count``); topics nobody subscribes to (``/truth`` without a viewer)
    never hold playback. Returns once some topic is matched, none is waited for and the graph
    has been unchanged for SETTLE_S (discovery of a subscriber's endpoints arrives in bursts),
    or after ``timeout`` s (with a warning naming the unmatched topics, if any). Returns the
    unmatched topics.
    """
    start = time.monotonic()
    last, since = None, start
    while True:
        now = time.monotonic()
        state = tuple((n, node.count_subscribers(n), p.get_subscription_count())
                      for n, p in sorted(pubs.items()))
        if state != last:
            last, since = state, now
        pending = [n for n, graph, matched in state if graph > matched]
        heard = any(matched for _, _, matched in state)
        if (heard and not pending and now - since >= SETTLE_S) or now - start >= timeout:
            break
        time.sleep(0.02)
    if pending:
        log(f'bag play: warning: subscribers not matched after {timeout:g} s on '
            f'{", ".join(pending)}; playing anyway')
    elif not quiet:
        matched = [n for n, _, m in state if m > 0]
        idle = [n for n, _, m in state if m == 0]
        log(f'bag play: matched subscribers on {len(matched)} topic(s)'
            + (f'; no subscriber on {", ".join(idle)}' if idle else ''))
    return pending


def _play_once(path, pubs, clock_pub, rate, period_ns, topics, quiet, log, again=False):
    """One pass over the bag; returns the number of messages published.

    ``again``: a pass of a loop after the first. The clock then jumps back before the first
    instant's data, not after them (a node would take them for data of the end of the bag):
    a generated clock always starts a pass; the bag's first /clock message is published
    first (and again at its place).

    A bag ``/clock`` message that cannot be read as a rosgraph_msgs/Clock
    (``malformed_cdr``, as ``bag process`` counts it: a node's clock subscription could not
    read it either) and a message the middleware refuses to publish (``publish_failed``,
    e.g. more bytes than its type can hold) are skipped and counted. After the first pass
    the skipped messages, and the topics of which another number of messages was read than
    metadata.yaml lists (bagio.BagReader.count_mismatches), are named in a warning through
    ``log``; a damaged storage file that cannot be read on raises ValueError (bagio).
    """
    from collections import Counter

    import rclpy
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rosbags.serde import SerdeError
    from rosgraph_msgs.msg import Clock
    from . import bagio
    from .ros_conversions import ns_to_time

    skipped = Counter()

    def clock_at(t_ns):
        if clock_pub is not None:
            clock_pub.publish(Clock(clock=ns_to_time(max(0, t_ns))))

    def readable_clock(raw):
        try:
            bagio.deserialize(raw, bagio.CLOCK)
        except SerdeError:
            skipped[bagio.CLOCK_TOPIC, 'malformed_cdr'] += 1
            return False
        return True

    def publish(topic, raw):
        try:
            pubs[topic].publish(raw)
        except _rclpy.RCLError:
            if not rclpy.ok():          # the context is gone: not this message's fault
                raise
            skipped[topic, 'publish_failed'] += 1
            return False
        return True

    count = 0
    if again and clock_pub is None and bagio.CLOCK_TOPIC in pubs:
        with bagio.BagReader(path) as reader:
            for m in reader.messages(topics={bagio.CLOCK_TOPIC}):
                if readable_clock(m.raw):
                    publish(bagio.CLOCK_TOPIC, m.raw)
                    break
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
                    count += publish(bagio.CLOCK_TOPIC, raw)
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
                if readable_clock(m.raw):
                    held_clock.append(m.raw)
            else:
                count += publish(m.topic, m.raw)
        for raw in held_clock:
            count += publish(bagio.CLOCK_TOPIC, raw)
        if current is not None:
            clock_at(current)
        mismatches = reader.count_mismatches()
    if not again:
        if skipped:
            log(f'bag play: warning: skipped {sum(skipped.values())} message(s) that cannot be '
                'published: ' + '; '.join(f'{t}: {r} {n}' for (t, r), n in sorted(
                    skipped.items())))
        text = bagio.count_warning(mismatches)
        if text:
            log(f'bag play: warning: {text}')
    return count
