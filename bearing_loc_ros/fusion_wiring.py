"""The fusion node's rclpy plumbing: bearing subscriptions in, publications out.

:class:`BearingInputs` keeps one ``<station>/bearing`` subscription per station (from the
``stations`` parameter and from discovery: a discovered topic once the discovery probe
process has seen a valid bearing on it, ``discovery_probe``), counts losses (the
middleware's message-lost events and gaps in a single publisher's sequence numbers) and
reports incompatible QoS.
:class:`FusionOutputs` owns the publishers and turns the core's epochs, accuracy maps and
diagnostics into messages (built by ``ros_conversions``). No numerics here: alignment,
solving, gating and the per-station counters live in ``bearing_loc_ros.core.fusion``.
"""

from functools import partial
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.event_handler import EventHandler, PublisherEventCallbacks, QoSPublisherEventType, \
    QoSSubscriptionEventType, SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.qos import qos_policy_name_from_kind
from sensor_msgs.msg import NavSatFix
from visualization_msgs.msg import MarkerArray

from .core.fusion import MODE_MULTISTATION, MODE_TMA
from .core.fusion.config import STATION_ID_RE
from .core.fusion.gating import LOW_CONFIDENCE
from .memory import HEAP
from .ros_common import keep_last_qos, topics_under_namespace
from .ros_conversions import (diagnostic_array, fix_markers_msg, fix_to_cdr, fix_to_msg,
                              fix_to_navsat, occupancy_grid_msg, track_to_msg)

BEARING_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
#: New subscriptions made per discovery scan at most (the executor stays responsive when
#: many publishers appear at once; the rest are taken on the next scans).
MAX_NEW_PER_SCAN = 16
#: The bearing subscriptions' middleware events, read by :meth:`BearingInputs.poll_events`.
INCOMPATIBLE_QOS = QoSSubscriptionEventType.RCL_SUBSCRIPTION_REQUESTED_INCOMPATIBLE_QOS
MESSAGE_LOST = QoSSubscriptionEventType.RCL_SUBSCRIPTION_MESSAGE_LOST
INCOMPATIBLE_TYPE = QoSSubscriptionEventType.RCL_SUBSCRIPTION_INCOMPATIBLE_TYPE
#: The publishers' middleware events, read by :meth:`FusionOutputs.poll_events`.
OFFERED_INCOMPATIBLE_QOS = QoSPublisherEventType.RCL_PUBLISHER_OFFERED_INCOMPATIBLE_QOS
PUBLISHER_INCOMPATIBLE_TYPE = QoSPublisherEventType.RCL_PUBLISHER_INCOMPATIBLE_TYPE


class PolledEvent(EventHandler):
    """A subscription's middleware event, read by :meth:`poll` instead of the wait set.

    rclpy puts every event handler of a subscription into the executor's wait set, whose
    Python bookkeeping is rebuilt on every wake-up: three handlers per station cost more than
    the bearing subscriptions themselves (at 50 stations they were about a third of the
    rclpy floor). The counts are cumulative in the middleware, so polling them once per
    diagnostics period loses nothing; ``callback(info)`` runs when the count changed.
    """

    def poll(self):
        """Take the event's status; call the callback when its total count changed."""
        self._ready_to_take_data = True    # take_data reads only after a wait set said so
        info = self.take_data()
        if info is not None and info.total_count_change > 0:
            self.callback(info)


def polled_events(node, handle, kinds):
    """:class:`PolledEvent` of each (event type, callback) in ``kinds`` on the subscription or
    publisher ``handle``; an event type the middleware does not support is left out (as
    rclpy leaves out its default handlers for it)."""
    out = []
    for kind, callback in kinds:
        try:
            out.append(PolledEvent(callback_group=node.default_callback_group,
                                   callback=callback, event_type=kind, parent_impl=handle))
        except UnsupportedEventTypeError:
            continue
    return out


class BearingInputs:
    """The bearing subscriptions of a fusion node and their loss bookkeeping.

    ``on_bearing(station, raw, info)`` receives each message as its CDR bytes (a raw
    subscription: ``ros_conversions.bearing_from_cdr`` reads them without building the rclpy
    message) with rclpy's message info.
    ``subs``: station -> Subscription; ``discovered``: stations found by discovery (not in
    the parameter); ``seq``: station -> last publication sequence number;
    ``single_publisher``: station -> exactly one publisher (sequence gaps valid);
    ``incompatible_qos``: station -> incompatible publishers seen (QoS events);
    ``probe``: a ``discovery_probe.ProbeProcess`` or None (discovery subscribes at once);
    ``candidates``: discovered topics with a publisher that are watched by the probe, not
    subscribed here; ``trusted``: candidates the probe found valid, subscribed on the next
    scans (at most MAX_NEW_PER_SCAN per scan). The
    middleware events (incompatible QoS or type, messages lost) are not in the executor's
    wait set: :meth:`poll_events` reads them (the node calls it before each diagnostics).
    """

    def __init__(self, node, core, qos, on_bearing, probe=None):
        self.node, self.core, self.qos, self.on_bearing = node, core, qos, on_bearing
        self.probe = probe
        self.candidates = set()     # discovered, with a publisher, not subscribed (probed)
        self.trusted = set()        # candidates the probe found valid, not subscribed yet
        self.subs = {}
        self.incompatible_qos = {}
        self.discovered = set()
        self.seq = {}
        self.single_publisher = {}
        self.events = {}

    def subscribe(self, station, wait=True):
        """Subscribe to ``<station>/bearing``; ``wait=False`` (discovered): the station is
        not waited for before it delivered a valid bearing."""
        if station in self.subs:
            return
        self.core.add_station(station, wait=wait)
        topic = f'{station}/bearing'
        on_bearing = self.on_bearing

        def deliver(raw, info):
            # A plain function: rclpy inspects the callback on every message, and unwrapping
            # a functools.partial there cost ~2 % of the node's CPU at 50 stations.
            on_bearing(station, raw, info)

        sub = self.subs[station] = self.node.create_subscription(
            PoseWithCovarianceStamped, topic, deliver, self.qos,
            event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False), raw=True)
        self.events[station] = polled_events(self.node, sub.handle, (
            (INCOMPATIBLE_QOS, partial(self._on_incompatible_qos, station)),
            (MESSAGE_LOST, partial(self._on_message_lost, station)),
            (INCOMPATIBLE_TYPE, partial(self._on_incompatible_type, station))))
        self.single_publisher[station] = False

    def unsubscribe(self, station):
        """Drop ``station``: its subscription, bookkeeping and core state."""
        for event in self.events.pop(station, ()):
            event.destroy()
        sub = self.subs.pop(station, None)
        if sub is not None:
            self.node.destroy_subscription(sub)
        self.discovered.discard(station)
        self.seq.pop(station, None)
        self.single_publisher.pop(station, None)
        self.incompatible_qos.pop(station, None)
        self.core.remove_station(station)

    def poll_events(self):
        """Read every subscription's middleware events (:class:`PolledEvent`)."""
        for events in self.events.values():
            for event in events:
                event.poll()

    def stop_probe(self):
        """Stop the discovery probe process (if any) and reap it."""
        if self.probe is not None:
            self.probe.stop()

    def probe_diagnostics(self):
        """The discovery probe's counters for /diagnostics ({} without a probe)."""
        p = self.probe
        if p is None:
            return {}
        return {'discovery_candidates': len(self.candidates),
                'discovery_probe_running': p.running, 'discovery_probe_starts': p.starts,
                'discovery_probe_failures': p.failures,
                'discovery_probe_garbage': p.garbage}

    def destroy_events(self):
        """Release the event handles (before the node and its subscriptions go)."""
        for events in self.events.values():
            for event in events:
                event.destroy()
        self.events.clear()

    def set_stations(self, stations, previous):
        """The ``stations`` parameter changed from ``previous`` to ``stations``."""
        for s in stations:
            self.subscribe(s)
        for s in set(previous) - set(stations):
            self.unsubscribe(s)

    def discover(self):
        """Subscribe to new */bearing topics under the namespace (at most
        MAX_NEW_PER_SCAN per scan); drop discovered stations whose publishers are gone once
        they are not alive (waiting: at once; alive: after station_timeout, when stale).

        With a ``probe`` (``discovery_probe.ProbeProcess``), a new topic is first watched by
        the probe process and subscribed here only once it delivered a valid bearing, so
        publishers that never send one cost this process no subscription."""
        node, log = self.node, self.node.get_logger()
        found = topics_under_namespace(node, '/bearing', BEARING_TYPE, STATION_ID_RE)
        if self.probe is not None:
            self.candidates = {station for station, name in found.items()
                               if station not in self.subs and node.count_publishers(name) > 0}
            self.trusted.update(self.probe.update(self.candidates))
            self.trusted &= self.candidates
            new = sorted(self.trusted)[:MAX_NEW_PER_SCAN]
            self.trusted.difference_update(new)
        else:
            new = [station for station, name in found.items()
                   if station not in self.subs and node.count_publishers(name) > 0]
            new = new[:MAX_NEW_PER_SCAN]
        for station in new:
            self.discovered.add(station)
            self.subscribe(station, wait=False)
            log.info(f'discovered station {station} ({found[station]})')
            if '/' in station:
                # as bag process warns: another namespace may hold another emitter's bearings
                log.warning(f'station {station} is a bearing topic of the nested namespace '
                            f'{station.rpartition("/")[0]}, fused with the others as one '
                            'network; if it holds another emitter\'s bearings, run one fusion '
                            'node per namespace or list the stations')
        for station in list(self.discovered):
            topic = f'{node.get_namespace().rstrip("/")}/{station}/bearing'
            gone = station not in found or node.count_publishers(topic) == 0
            if gone and self.core.station_state(station) != 'alive':
                self.unsubscribe(station)
                log.info(f'station {station} left (no publisher on {topic})')
        HEAP.update(self, len(self.subs), log)  # departed stations' freed heap to the system

    def count_publishers(self):
        """Refresh which stations have exactly one publisher (sequence gaps are counted for
        those only: several publishers interleave their sequence numbers)."""
        ns = self.node.get_namespace().rstrip('/')
        for station in self.subs:
            one = self.node.count_publishers(f'{ns}/{station}/bearing') == 1
            if one != self.single_publisher.get(station):
                self.seq.pop(station, None)     # a new baseline after the change
            self.single_publisher[station] = one

    def count_sequence(self, station, info):
        """Count a gap in ``station``'s publication sequence numbers (rclpy message
        ``info``) as ``lost.sequence_gap`` when the station has a single publisher."""
        seq = info.get('publication_sequence_number')
        if seq is not None:
            last = self.seq.get(station)
            if last is not None and seq > last + 1 and self.single_publisher.get(station):
                self.core.count_lost(station, 'sequence_gap', seq - last - 1)
            self.seq[station] = seq

    def _on_message_lost(self, station, info):
        """The middleware reports messages of ``station`` lost (for example a sequence gap
        seen by a best-effort reader)."""
        self.core.count_lost(station, 'message_lost', int(info.total_count_change))

    def _on_incompatible_qos(self, station, info):
        """A publisher on <station>/bearing cannot match (typically best-effort vs reliable)."""
        self.incompatible_qos[station] = int(info.total_count)
        self.node.get_logger().warning(
            f'{station}/bearing: {info.total_count} publisher(s) with incompatible QoS (policy '
            f'{info.last_policy_kind}); a best-effort publisher needs qos_reliability:='
            'best_effort here, or a reliable publisher', throttle_duration_sec=10.0)

    def _on_incompatible_type(self, station, info):
        """A publisher on <station>/bearing has another message type."""
        self.node.get_logger().warning(
            f'{station}/bearing: a publisher with another message type than '
            f'{BEARING_TYPE}; no messages will be received from it',
            throttle_duration_sec=10.0)


class FusionOutputs:
    """The fusion node's publishers (module docstring of ``fusion_node``) and counters.

    ``p``: the node's parameter values; ``accuracy_map``: a core.display.AccuracyMap or
    None; ``ray_length``, ``ellipsoid_sigma``: the run-time display parameters.
    The publishers' middleware events (a subscriber requesting incompatible QoS, or with
    another type) are polled like the inputs' (:meth:`poll_events`, before each
    diagnostics) and logged with rclpy's default warnings: as event handlers they would be
    two entities per publisher in every wait set.
    """

    def __init__(self, node, p, mode, frame_id, geodetic_origin, accuracy_map):
        pub = self._publisher
        self.node, self.frame_id, self.geodetic_origin = node, frame_id, geodetic_origin
        self.events = []
        self.ray_length = p['marker_ray_length']
        self.ellipsoid_sigma = p['ellipsoid_sigma']
        self.fix_pub = pub(PoseWithCovarianceStamped, 'fix', 10)
        self.navsat_pub = pub(NavSatFix, 'fix/navsat', 10) if geodetic_origin is not None \
            else None
        self.marker_pub = pub(MarkerArray, 'markers', 10) if p['publish_markers'] else None
        # Fixes that failed their consistency checks (core.robust): never on fix; here only
        # when asked for.
        self.low_confidence_pub = (pub(PoseWithCovarianceStamped, 'fix/low_confidence', 10)
                                   if p['publish_low_confidence'] else None)
        self.diag_pub = pub(DiagnosticArray, '/diagnostics', 10)
        self.track_pub = pub(Odometry, 'track', 10) if mode == MODE_TMA else None
        self.accuracy_map = accuracy_map
        self.map_pub = None
        self.fixes_published = 0
        self.accuracy_maps = 0          # maps published
        self.accuracy_map_ms = None     # wall time of the last map computation
        self._map_logged = (None, 0.0)  # (station names, time.monotonic()) of the last log
        if accuracy_map is not None and mode == MODE_MULTISTATION:
            self.map_pub = pub(OccupancyGrid, 'accuracy_map', keep_last_qos(1, latched=True))

    def _publisher(self, msg_type, topic, qos):
        """A publisher whose middleware events are polled (:class:`PolledEvent`)."""
        publisher = self.node.create_publisher(
            msg_type, topic, qos,
            event_callbacks=PublisherEventCallbacks(use_default_callbacks=False))
        name = publisher.topic_name
        self.events += polled_events(self.node, publisher.handle, (
            (OFFERED_INCOMPATIBLE_QOS, partial(self._on_incompatible_qos, name)),
            (PUBLISHER_INCOMPATIBLE_TYPE, partial(self._on_incompatible_type, name))))
        return publisher

    def poll_events(self):
        """Read every publisher's middleware events (:class:`PolledEvent`)."""
        for event in self.events:
            event.poll()

    def destroy_events(self):
        """Release the event handles (before the node and its publishers go)."""
        for event in self.events:
            event.destroy()
        self.events.clear()

    def _on_incompatible_qos(self, topic, info):
        """A subscriber of ``topic`` requests QoS this publisher does not offer."""
        self.node.get_logger().warning(
            f"New subscription discovered on topic '{topic}', requesting incompatible QoS. "
            'No messages will be sent to it. Last incompatible policy: '
            f'{qos_policy_name_from_kind(info.last_policy_kind)}')

    def _on_incompatible_type(self, topic, info):
        """A subscriber of ``topic`` has another message type."""
        self.node.get_logger().warning(
            f"Incompatible type on topic '{topic}', no messages will be sent to it.")

    def publish_epochs(self, epochs, station_timeout):
        """Publish the epochs' fixes first (the latency-critical output), then the rest
        (low-confidence fixes, track, navsat, markers; ``station_timeout`` s: the marker
        lifetime)."""
        fixes = [ep for ep in epochs if ep.ok]
        for ep in fixes:
            self.fix_pub.publish(fix_to_cdr(ep.position, ep.covariance, ep.stamp_ns,
                                            self.frame_id))
            self.fixes_published += 1
        log = self.node.get_logger()
        for ep in epochs:
            if self.low_confidence_pub is not None and ep.reason == LOW_CONFIDENCE \
                    and ep.position is not None:
                self.low_confidence_pub.publish(fix_to_msg(ep.position, ep.covariance,
                                                           ep.stamp_ns, self.frame_id))
            if not ep.ok:
                log.debug(f'epoch {ep.stamp_ns / 1e9:.3f}: no fix ({ep.reason}'
                          f'{": " + ep.detail if ep.detail else ""})')
        # Markers cost ~0.5-1.5 ms per fix at N = 10: built only when someone listens.
        markers = self.marker_pub is not None and self.marker_pub.get_subscription_count() > 0
        for ep in fixes:
            if self.track_pub is not None and ep.velocity is not None:
                self.track_pub.publish(track_to_msg(ep.position, ep.velocity,
                                                    ep.state_covariance, ep.stamp_ns,
                                                    self.frame_id))
            if self.navsat_pub is not None:
                try:
                    self.navsat_pub.publish(fix_to_navsat(ep.position, ep.covariance,
                                                          ep.stamp_ns, self.geodetic_origin,
                                                          self.frame_id))
                except ValueError as exc:
                    log.warning(f'fix/navsat: {exc}', throttle_duration_sec=5.0)
            if markers:
                self.marker_pub.publish(fix_markers_msg(
                    ep, self.frame_id, self.ray_length, self.ellipsoid_sigma,
                    int(station_timeout * 1e9)))
            if ep.rejected:
                log.info(f'epoch {ep.stamp_ns / 1e9:.3f}: outlier bearing(s) from '
                         f'{", ".join(b.station for b in ep.rejected)} rejected',
                         throttle_duration_sec=5.0)

    def publish_accuracy_map(self, geometry, now_ns):
        """Publish the expected-accuracy OccupancyGrid when core.display.AccuracyMap says the
        live station ``geometry`` changed (run from the tick, never per bearing)."""
        log = self.node.get_logger()
        t0 = time.perf_counter()
        try:
            out = self.accuracy_map.update(geometry)
        except ValueError as exc:
            log.warning(f'accuracy_map: {exc}', throttle_duration_sec=10.0)
            return
        if out is None:
            return
        grid, data = out
        self.map_pub.publish(occupancy_grid_msg(grid, data, now_ns, self.frame_id))
        self.accuracy_maps += 1
        self.accuracy_map_ms = 1e3 * (time.perf_counter() - t0)
        # A new station set is logged at once; a recomputation for moved stations of the same
        # set (mobile stations: every tick) at most every 10 s.
        names, wall = tuple(self.accuracy_map.stations), time.monotonic()
        if names != self._map_logged[0] or wall - self._map_logged[1] >= 10.0:
            self._map_logged = (names, wall)
            log.info(f'accuracy_map: {len(names)} live station(s) ({", ".join(names)}), '
                     f'{grid.width}x{grid.height} cells of {grid.resolution:g} m, '
                     f'{self.accuracy_map_ms:.1f} ms')

    def publish_diagnostics(self, entries, now_ns, incompatible_qos):
        """Publish the core's diagnostic ``entries`` (overall first, then one per station)
        with the map counters and the stations' incompatible QoS publishers added."""
        if self.map_pub is not None:
            entries[0].values.update(accuracy_maps=self.accuracy_maps, accuracy_map_ms=(
                'n/a' if self.accuracy_map_ms is None else f'{self.accuracy_map_ms:.1f}'))
        for d in entries[1:]:
            if d.hardware_id in incompatible_qos:
                d.values['incompatible_qos_publishers'] = incompatible_qos[d.hardware_id]
        self.diag_pub.publish(diagnostic_array(
            entries, self.node.get_fully_qualified_name().lstrip('/'), now_ns))
