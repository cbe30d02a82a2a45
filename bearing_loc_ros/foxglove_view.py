"""A Foxglove WebSocket server of the package's topics (foxglove-sdk), live or from a bag.

Used by the ``view_node`` node (live topics over DDS) and by ``bearing_loc view --bag``
(recorded topics). What it serves (WebSocket subprotocol ``foxglove.sdk.v1`` of
foxglove-sdk, understood by Foxglove and by Lichtblick releases that speak it):

* every forwarded ROS topic as a channel with ``cdr`` message encoding and a ``ros2msg``
  schema (:mod:`bearing_loc_ros.msgdefs`); the CDR bytes are forwarded unchanged;
* ``accuracy_map`` (and every other latched channel: ``/map_geojson`` and the stations'
  ``navsat``) is sent to each new subscriber, to that client alone (foxglove-sdk's per-sink
  log; the sink id of a WebSocket client is its client id), so late joiners get the
  transient-local map and the clients already subscribed get nothing twice;
* ``/map_geojson`` (foxglove schema ``foxglove.GeoJSON``, as foxglove-sdk ships it): the
  current picture for the Map panel (stations, last bearing rays, last fix, its error
  ellipse and the fix trail, :class:`~bearing_loc_ros.core.gis.LivePicture`), at most every
  ``geojson_period`` s, when a geodetic origin is set. Only fixes and bearings in the world
  frame ``frame_id`` that :class:`~bearing_loc_ros.core.gis.LivePicture` can draw are used;
  the others, and inputs older than what the picture holds (out of order), are counted in
  ``dropped`` / ``rejected`` (:meth:`FoxgloveView.stats`) and logged at most once per
  :data:`LOG_THROTTLE_S` per reason. A stamp going back by more than
  :data:`~bearing_loc_ros.core.gis.CLOCK_JUMP_NS` is a clock restart (bag replayed, simulation
  restarted, an earlier stamp in the future): the picture starts afresh from it. One picture
  per namespace (:func:`namespace_of`: ``<ns>/fix`` and ``<ns>/<station>/bearing``, the
  fusion node's channels) on ``<ns>/map_geojson``, the root namespace's on
  ``/map_geojson``;
* ``/<station>/navsat`` (sensor_msgs/NavSatFix, latched) for every station seen in a bearing
  message, when a geodetic origin is set;
* ``/view/fix_stats`` (JSON, schema :data:`STATS_SCHEMA_NAME`): for every fix in the world
  frame, its σ (sqrt of the covariance diagonal and horizontal sqrt(C_xx + C_yy), m) and the
  fix rate (fixes per second of fix stamps over the last :data:`RATE_WINDOW_NS`,
  :class:`~bearing_loc_ros.core.gis.FixRate`), for the layout's plot; per namespace as the
  picture (``<ns>/view/fix_stats``);
* the server time (Foxglove ``time`` capability) from ``/clock`` when ``use_time`` is set
  (a node running with ``use_sim_time``, or a bag).

Slow clients: foxglove-sdk queues at most ``backlog`` messages per client and drops the
oldest data message when the queue is full, so a stalled client costs bounded memory. Its
per-message send errors of a client that went away (``Broken pipe``, up to ``backlog``
lines) are logged once per client and :data:`LOG_THROTTLE_S`.
"""

from collections import Counter
import importlib
import json
import logging
import math
import sys
import threading
import time

from .core import gis
from .log_throttle import LOG_THROTTLE_S, Throttle  # noqa: F401 (LOG_THROTTLE_S re-exported)

#: Topic of the GeoJSON picture.
GEOJSON_TOPIC = '/map_geojson'
#: Leaf names (last path component) of the package's topics that are forwarded by default.
DEFAULT_LEAVES = ('bearing', 'fix', 'navsat', 'markers', 'accuracy_map', 'track', 'truth')
DEFAULT_GLOBAL = ('/diagnostics', '/clock')
#: Topics whose last message is sent again to every new subscriber.
LATCHED_LEAVES = ('accuracy_map',)
CLOCK_TYPE = 'rosgraph_msgs/msg/Clock'
BEARING_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
DEFAULT_BACKLOG = 512
STATS_TOPIC = '/view/fix_stats'
STATS_SCHEMA_NAME = 'bearing_loc_ros.FixStats'
RATE_WINDOW_NS = gis.RATE_WINDOW_NS
#: foxglove-sdk's logger of per-client send/receive errors (pyo3-log name of the Rust module).
SDK_CLIENT_LOGGER = 'foxglove.websocket.connected_client.poller'
STATS_SCHEMA = {'type': 'object', 'properties': {
    k: {'type': 'number'} for k in ('stamp_s', 'sigma_east_m', 'sigma_north_m', 'sigma_up_m',
                                    'sigma_horizontal_m', 'sigma_3d_m', 'fix_rate_hz')}}
STATS_SCHEMA['properties']['stamp_ns'] = {'type': 'integer'}


class _ClientErrorFilter(logging.Filter):
    """Throttles foxglove-sdk's per-message errors of one client ('Error sending message to
    client ADDR: ...'): one line per client and kind per :data:`LOG_THROTTLE_S`."""

    def __init__(self):
        super().__init__()
        self.throttle = Throttle()

    def filter(self, record):
        text = record.getMessage()
        left = self.throttle.allow(text.split(': ', 1)[0])
        if left is None:
            return False
        if left:
            record.msg, record.args = f'{text} ({left} similar lines left out)', None
        return True


_CLIENT_FILTER = _ClientErrorFilter()


def throttle_sdk_client_errors():
    """Install the :class:`_ClientErrorFilter` on foxglove-sdk's client logger (idempotent)."""
    logger = logging.getLogger(SDK_CLIENT_LOGGER)
    if _CLIENT_FILTER not in logger.filters:
        logger.addFilter(_CLIENT_FILTER)


def _stderr_log(text):
    print(f'view: {text}', file=sys.stderr, flush=True)


def wanted_topic(topic, msgtype, leaves=DEFAULT_LEAVES, extra=DEFAULT_GLOBAL):
    """True for a topic the view forwards by default (a package topic)."""
    if topic in extra:
        return True
    leaf = topic.rstrip('/').rsplit('/', 1)[-1]
    return leaf in leaves


def message_class(msgtype):
    """The rclpy message class of 'pkg/msg/Type' (ValueError when not installed)."""
    from .msgdefs import split_type
    pkg, name = split_type(msgtype)
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError):
        raise ValueError(f'{msgtype}: message package not installed') from None


def station_of(topic):
    """Station of a '<ns>/<station>/bearing' topic with its namespace, without the leading
    '/' ('/station_1/bearing': 'station_1'; '/uhf/north/bearing': 'uhf/north'), else None.
    Keyed so, one station heard on two channels is two stations."""
    parts = topic.strip('/').split('/')
    if len(parts) >= 2 and parts[-1] == 'bearing':
        return '/'.join(parts[:-1])
    return None


def namespace_of(topic):
    """Namespace of the picture a fix or bearing topic belongs to, without leading '/' ('' is
    the root): '<ns>/fix' and '<ns>/<station>/bearing' are namespace '<ns>'; else None.

    One picture per namespace keeps the channels of a receiver apart ('/uhf/fix' and
    '/uhf/<station>/bearing' in namespace 'uhf', as the fusion node's ``channels``
    publish them; docs/nodes.md "Several channels")."""
    parts = topic.strip('/').split('/')
    if parts[-1] == 'fix':
        return '/'.join(parts[:-1])
    if parts[-1] == 'bearing' and len(parts) >= 2:
        return '/'.join(parts[:-2])
    return None


def space_topic(namespace, topic):
    """A view topic of a namespace's picture: '/map_geojson' in 'uhf' is '/uhf/map_geojson'
    (the root keeps the topic)."""
    return f'/{namespace}{topic}' if namespace else topic


class _Space:
    """What the view keeps per picture namespace (:func:`namespace_of`): the picture (None
    without an origin), its fix rate, its /map_geojson and /view/fix_stats channels and the
    monotonic time of its last picture."""

    def __init__(self, view, namespace):
        from foxglove import Channel, Schema
        self.namespace = namespace
        self.picture = (gis.LivePicture(view.origin, view.probability) if view.origin
                        else None)
        self.fix_rate = gis.FixRate(RATE_WINDOW_NS)
        self.stats_channel = Channel(
            space_topic(namespace, STATS_TOPIC), message_encoding='json',
            context=view.context,
            schema=Schema(name=STATS_SCHEMA_NAME, encoding='jsonschema',
                          data=json.dumps(STATS_SCHEMA).encode('utf-8')))
        self.geo_channel = None
        if self.picture is not None:
            from foxglove.channels import GeoJsonChannel
            self.geo_channel = GeoJsonChannel(space_topic(namespace, GEOJSON_TOPIC),
                                              context=view.context)
        self.last_geojson = 0.0


class FoxgloveView:
    """Channels, forwarding, latched re-send and the map picture (module docstring).

    One picture per namespace (:func:`namespace_of`): the root's on ``/map_geojson`` and
    ``/view/fix_stats``, namespace ``uhf``'s on ``/uhf/map_geojson`` and
    ``/uhf/view/fix_stats`` (created with the namespace's first fix or bearing topic).
    Thread-safe: :meth:`forward` may be called from any thread; the server's listener
    callbacks run on foxglove-sdk's threads. ``frame_id``: the world frame of the ENU
    picture; fixes and bearings in any other frame are not drawn. ``log(text)``: warnings
    (default: standard error), already throttled.
    """

    def __init__(self, host='127.0.0.1', port=8765, name='bearing_loc_ros', origin=None,
                 use_time=False, backlog=DEFAULT_BACKLOG, geojson_period=0.5,
                 probability=gis.DEFAULT_PROBABILITY, frame_id='map', log=None):
        import foxglove
        from foxglove.websocket import Capability, ServerListener

        self.log = log or _stderr_log
        self.frame_id = frame_id
        self.origin = gis.check_origin(origin) if origin else None
        gis.ellipse_scale(probability)
        self.probability = float(probability)
        self.geojson_period = float(geojson_period)
        self._lock = threading.Lock()
        self._channels = {}       # topic -> foxglove Channel
        self._types = {}          # topic -> msgtype
        self._latched = {}        # channel id -> (channel, payload, log_time)
        self._latched_topics = set()
        self._spaces = {}         # namespace -> _Space
        self._station_pos = {}    # station -> last position tuple published as NavSatFix
        self.forwarded = 0
        self.forwarded_bytes = 0
        self.dropped = 0          # messages the picture could not use (counted)
        self.rejected = Counter()  # reason -> messages not used (dropped by reason)
        self.clock_restarts = 0
        self.subscriptions = 0
        self.time_ns = None
        self._throttle = Throttle()
        self.context = foxglove.Context()
        root = self._space('')
        # The root picture's (the only one without channels), as attributes for callers.
        self.picture, self._geo_channel = root.picture, root.geo_channel
        throttle_sdk_client_errors()
        view = self

        class Listener(ServerListener):
            def on_subscribe(self, client, channel):
                view._on_subscribe(client.id, channel.id)

        caps = [Capability.Time] if use_time else []
        self.server = foxglove.start_server(
            name=name, host=host, port=int(port), capabilities=caps,
            server_listener=Listener(), context=self.context,
            message_backlog_size=int(backlog))

    def _space(self, namespace):
        """The :class:`_Space` of a namespace, created on first use."""
        with self._lock:
            space = self._spaces.get(namespace)
            if space is None:
                space = self._spaces[namespace] = _Space(self, namespace)
            return space

    @property
    def port(self):
        """The TCP port the server listens on (useful with port 0)."""
        return self.server.port

    # ------------------------------------------------------------------------------ channels

    def _channel(self, topic, msgtype):
        ch = self._channels.get(topic)
        if ch is not None:
            if self._types[topic] != msgtype:
                raise ValueError(f'{topic}: type changed from {self._types[topic]} to {msgtype}')
            return ch
        from foxglove import Channel, Schema
        from .msgdefs import message_definition
        schema = Schema(name=msgtype, encoding='ros2msg',
                        data=message_definition(msgtype).encode('utf-8'))
        ch = Channel(topic, schema=schema, message_encoding='cdr', context=self.context)
        self._channels[topic] = ch
        self._types[topic] = msgtype
        leaf = topic.rstrip('/').rsplit('/', 1)[-1]
        if leaf in LATCHED_LEAVES:
            self._latched_topics.add(topic)
        return ch

    def _remember(self, topic, channel, payload, log_time):
        if topic in self._latched_topics:
            self._latched[channel.id()] = (channel, payload, log_time)

    def _on_subscribe(self, client_id, channel_id):
        """A client subscribed: send the channel's latched message to that client alone (its
        sink id is its client id)."""
        with self._lock:
            self.subscriptions += 1
            item = self._latched.get(channel_id)
            if item is None:
                return
            channel, payload, log_time = item
            channel.log(payload, log_time=log_time, sink_id=client_id)

    # ----------------------------------------------------------------------------- messages

    def advertise(self, topic, msgtype):
        """Create (advertise) the channel of a topic before its first message arrives."""
        with self._lock:
            self._channel(topic, msgtype)

    def forward(self, topic, msgtype, raw, log_time_ns):
        """Forward one CDR message unchanged; update clock, picture and station positions."""
        raw = bytes(raw)
        log_time_ns = int(log_time_ns)
        with self._lock:
            ch = self._channel(topic, msgtype)
            ch.log(raw, log_time=log_time_ns)
            self._remember(topic, ch, raw, log_time_ns)
            self.forwarded += 1
            self.forwarded_bytes += len(raw)
        if msgtype == CLOCK_TYPE and topic == '/clock':
            self._on_clock(raw)
        elif msgtype == BEARING_TYPE:
            self._observe(topic, raw, log_time_ns)

    def set_time(self, stamp_ns):
        """Broadcast the server time (Foxglove ``time`` capability)."""
        self.time_ns = int(stamp_ns)
        self.server.broadcast_time(self.time_ns)

    def _on_clock(self, raw):
        from rclpy.serialization import deserialize_message
        from rosgraph_msgs.msg import Clock
        from .ros_conversions import time_to_ns
        try:
            self.set_time(time_to_ns(deserialize_message(raw, Clock).clock))
        except Exception as exc:  # a malformed /clock message: counted, never fatal
            self._drop('/clock', 'malformed', str(exc) or type(exc).__name__)

    def _warn(self, key, text):
        left = self._throttle.allow(key)
        if left is not None:
            self.log(text + (f' ({left} similar lines left out)' if left else ''))

    def _drop(self, topic, reason, detail):
        """Count a message the picture does not use, and log it (throttled per reason)."""
        self.dropped += 1
        self.rejected[reason] += 1
        self._warn(reason, f'{topic}: message not used ({reason}: {detail}); '
                           f'{self.rejected[reason]} {reason} so far')

    def _ordered(self, topic, order, stamp_ns):
        """Count and log a :class:`~bearing_loc_ros.core.gis.LivePicture` time-order result."""
        if order == gis.OUT_OF_ORDER:
            self._drop(topic, 'out_of_order', f'stamp {stamp_ns / 1e9:.3f} s is older than '
                       'what the map shows')
        elif order == gis.RESTARTED:
            self.clock_restarts += 1
            self._warn('clock_restart', f'{topic}: stamp {stamp_ns / 1e9:.3f} s went back by '
                       f'more than {gis.CLOCK_JUMP_NS / 1e9:g} s: clock restart, the map '
                       f'starts again ({self.clock_restarts} so far)')

    def _observe(self, topic, raw, log_time_ns):
        """A fix or bearing message: validated (world frame, drawable) before it reaches the
        fix statistics and the picture; anything else is counted and logged (throttled)."""
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from rclpy.serialization import deserialize_message
        from .ros_conversions import bearing_from_msg, fix_from_msg
        leaf = topic.rstrip('/').rsplit('/', 1)[-1]
        namespace = namespace_of(topic)
        if namespace is None or leaf == 'bearing' and self.origin is None:
            return
        try:
            msg = deserialize_message(raw, PoseWithCovarianceStamped)
        except Exception as exc:  # malformed CDR: counted, never fatal
            self._drop(topic, 'malformed', str(exc) or type(exc).__name__)
            return
        frame = msg.header.frame_id
        if frame != self.frame_id:
            self._drop(topic, 'wrong_frame', f'frame_id {frame!r}; the map draws frame '
                       f'{self.frame_id!r} only')
            return
        try:
            if leaf == 'fix':
                stamp, pos, cov = fix_from_msg(msg)
                # The fix message carries no status, estimator or stations: none are drawn.
                item = gis.GeoFix(stamp, pos, cov, None, None, None)
                gis.check_live_fix(item, self.origin)
            else:
                item = bearing_from_msg(msg, station_of(topic), expected_frame=self.frame_id)
                gis.check_live_bearing(item)
        except ValueError as exc:  # contract-breaking message: counted, never fatal
            self._drop(topic, getattr(exc, 'reason', f'bad_{leaf}'), str(exc))
            return
        space = self._space(namespace)
        if leaf == 'fix':
            order = self._fix_stats(space, item.stamp_ns, item.covariance, log_time_ns)
            if space.picture is not None:
                order = space.picture.update_fix(item)
        else:
            order = space.picture.update_bearing(item)
            if order != gis.OUT_OF_ORDER:
                self._station_navsat(topic, item, log_time_ns)
        self._ordered(topic, order, item.stamp_ns)
        self._publish_space(space, log_time_ns)

    def _fix_stats(self, space, stamp, cov, log_time_ns):
        """Log σ (m) and the fix rate (Hz, :class:`~bearing_loc_ros.core.gis.FixRate`) of a
        fix on its namespace's fix_stats; return the rate's time-order result."""
        rate, order = space.fix_rate.add(stamp)
        d = [float(cov[i, i]) for i in range(3)]

        def root(v):
            return math.sqrt(v) if math.isfinite(v) and v >= 0 else None
        space.stats_channel.log({
            'stamp_ns': int(stamp), 'stamp_s': stamp / 1e9, 'sigma_east_m': root(d[0]),
            'sigma_north_m': root(d[1]), 'sigma_up_m': root(d[2]),
            'sigma_horizontal_m': root(d[0] + d[1]),
            'sigma_3d_m': root(sum(d)),
            'fix_rate_hz': rate},
            log_time=log_time_ns)
        return order

    def restart(self):
        """Start every picture and fix rate afresh (a bag replayed again)."""
        for space in list(self._spaces.values()):
            if space.picture is not None:
                space.picture.reset()
            space.fix_rate = gis.FixRate(RATE_WINDOW_NS)

    def _station_navsat(self, topic, b, log_time_ns):
        """Publish a station's position as NavSatFix when it is new or moved."""
        key = tuple(float(v) for v in b.position)
        if self._station_pos.get(b.station) == key:
            return
        from rclpy.serialization import serialize_message
        from .ros_conversions import fix_to_navsat
        msg = fix_to_navsat(b.position, b.position_covariance, b.stamp_ns, self.origin,
                            self.frame_id)
        self._station_pos[b.station] = key
        navsat = topic[:-len('bearing')] + 'navsat'
        self._latched_topics.add(navsat)      # the view's own station topic (not fix/navsat)
        self.forward(navsat, 'sensor_msgs/msg/NavSatFix', serialize_message(msg), log_time_ns)

    def publish_geojson(self, log_time_ns, force=False):
        """Send each namespace's current picture on its /map_geojson (rate-limited per
        picture unless ``force``); True when any was sent."""
        sent = False
        for space in list(self._spaces.values()):
            sent |= self._publish_space(space, log_time_ns, force)
        return sent

    def _publish_space(self, space, log_time_ns, force=False):
        """Send one namespace's picture when it changed (or ``force``), at most every
        ``geojson_period`` s unless ``force``."""
        picture = space.picture
        if picture is None or not (picture.changed or force):
            return False
        now = time.monotonic()
        if not force and now - space.last_geojson < self.geojson_period:
            return False
        from foxglove.messages import GeoJson
        from .gis_export import geojson_text
        try:
            text = geojson_text(picture.collection())
        except ValueError as exc:
            # Never again (inputs are checked), but a picture that cannot be drawn must not
            # stop the map: it is dropped and the map starts afresh.
            picture.reset()
            self._drop(space_topic(space.namespace, GEOJSON_TOPIC), 'undrawable',
                       f'{exc}; the map starts again')
            return False
        msg = GeoJson(geojson=text)
        with self._lock:
            space.geo_channel.log(msg, log_time=int(log_time_ns))
            self._latched[space.geo_channel.id()] = (space.geo_channel, msg, int(log_time_ns))
        space.last_geojson = now
        return True

    def stats(self):
        """Counters: forwarded messages/bytes, channels, subscriptions, dropped (messages the
        picture or the fix statistics did not use), rejected (dropped by reason: wrong_frame,
        out_of_order, bad_fix, malformed, the bearing contract's reasons...) and
        clock_restarts."""
        return {'forwarded': self.forwarded, 'forwarded_bytes': self.forwarded_bytes,
                'channels': len(self._channels), 'subscriptions': self.subscriptions,
                'dropped': self.dropped, 'rejected': dict(self.rejected),
                'clock_restarts': self.clock_restarts}

    def stop(self):
        """Stop the server (idempotent)."""
        self.server.stop()


def bag_plan(paths, topics=None):
    """The requested topics that no bag of ``paths`` holds (sorted); ValueError when the
    bags list no message to forward.

    The counts are those metadata.yaml lists (:class:`bearing_loc_ros.bagio.BagReader`);
    ``topics``: forward only these (default: all). A bag that cannot be opened raises its
    one-line ValueError.
    """
    from . import bagio
    counts = {}
    for p in paths:
        with bagio.BagReader(p) as r:
            for name, info in r.topics.items():
                counts[name] = counts.get(name, 0) + info.count
    missing = sorted(set(topics or ()) - set(counts))
    if not sum(n for name, n in counts.items() if not topics or name in topics):
        which = f' on the topics {", ".join(sorted(topics))}' if topics else ''
        absent = f' (no bag has {", ".join(missing)})' if missing else ''
        raise ValueError(f'bag: {" + ".join(map(str, paths))} holds no message{which} to '
                         f'serve{absent}')
    return missing


def serve_bag(view, paths, rate=1.0, loop=False, stop=None, topics=None, log=print):
    """Forward the messages of one or more bags (merged by bag time) at ``rate`` x real time.

    Raw CDR bytes from :class:`bearing_loc_ros.bagio.BagReader`; the server time follows
    ``/clock`` when the bag has it, else the bag time of each message. ``stop``: a
    threading.Event that ends the replay (checked before every pass and every message);
    ``topics``: forward only these (default: all); a requested topic that no bag holds is
    named in a warning through ``log``. ValueError, before anything is served, when the bags
    list no message to forward (:func:`bag_plan`). With ``loop`` every pass after the first
    starts the picture afresh (:meth:`FoxgloveView.restart`): the bag's stamps start again;
    a pass that forwards nothing (the storage holds fewer messages than listed) ends the
    replay instead of starting another. The picture is published once more at the end of a
    pass, with the log time of the pass's last message. Returns the number of messages
    forwarded.
    """
    import heapq
    from . import bagio
    if not rate > 0:
        raise ValueError(f'rate: must be > 0, got {rate}')
    missing = bag_plan(paths, topics)
    if missing:
        log(f'view: warning: no bag has the requested topic(s) {", ".join(missing)}; '
            'they are not served')
    stop = stop or threading.Event()
    sent = 0
    passes = 0
    while not stop.is_set():
        if passes:
            view.restart()
        passes += 1
        sent_before = sent
        readers = [bagio.BagReader(p) for p in paths]
        try:
            for r in readers:
                r.open()
            has_clock = any(bagio.CLOCK_TOPIC in r.topics for r in readers)
            for r in readers:
                for name, info in r.topics.items():
                    if not topics or name in topics:
                        view.advertise(name, info.msgtype)
            streams = [r.messages() for r in readers]
            merged = heapq.merge(*streams, key=lambda m: m.log_time_ns)
            t0_bag = t0_wall = t_last = None
            for m in merged:
                if stop.is_set():
                    return sent
                if topics and m.topic not in topics:
                    continue
                if t0_bag is None:
                    t0_bag, t0_wall = m.log_time_ns, time.monotonic()
                due = t0_wall + (m.log_time_ns - t0_bag) / 1e9 / rate
                delay = due - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    return sent
                view.forward(m.topic, m.msgtype, m.raw, m.log_time_ns)
                if not has_clock:
                    view.set_time(m.log_time_ns)
                t_last = m.log_time_ns
                sent += 1
            if t_last is not None:
                view.publish_geojson(t_last, force=True)
        finally:
            for r in readers:
                r.close()
        if not loop:
            return sent
        if sent == sent_before:
            log('view: warning: a pass forwarded no message (the bags hold fewer than '
                'metadata.yaml lists); not replaying again')
            return sent
        log(f'view: {sent} messages forwarded; replaying again')
    return sent
