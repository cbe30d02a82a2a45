"""One side of the lossy-link test (test_lossy_link.py), run in its own network namespace.

``python lossy_link_peer.py stations QOS SECONDS``: four stations publish noisy bearings of
a fixed target on ``/lossy/s<k>/bearing`` at 10 Hz, all stamped on the same 0.1 s grid of
the wall clock (stations observing together), with reliability QOS (best_effort or
reliable).

``python lossy_link_peer.py fusion QOS SECONDS``: a fusion node (namespace ``/lossy``,
stations s1-s4, qos_reliability QOS) runs for SECONDS; prints one JSON object: the bearings
delivered to it (stamp -> count), its fixes (stamp, position, covariance) and its
diagnostics' loss counters.
"""
import inspect
import json
import sys
import time

import numpy as np

PERIOD_NS = 100_000_000
TARGET = [2500.0, 3000.0, 800.0]
POSITIONS = {'s1': [0.0, 0.0, 0.0], 's2': [5000.0, 0.0, 20.0], 's3': [0.0, 6000.0, 40.0],
             's4': [6000.0, 6000.0, 10.0]}
SIGMA = 3e-3


def run_stations(qos, seconds):
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from bearing_loc_ros.core.bearings import Bearing
    from bearing_loc_ros.core.conventions import azimuth_elevation
    from bearing_loc_ros.ros_common import keep_last_qos
    from bearing_loc_ros.ros_conversions import bearing_to_msg

    # A paced synthetic-station loop like bench/soak_fusion.py's, kept here on purpose: this
    # peer is a self-contained script the lossy-link test starts, with its own QoS and seed.
    rclpy.init()
    node = rclpy.create_node('stations', namespace='/lossy')
    pubs = {s: node.create_publisher(PoseWithCovarianceStamped, f'{s}/bearing',
                                     keep_last_qos(10, qos)) for s in POSITIONS}
    rng = np.random.default_rng(7)
    end = time.time() + seconds
    k = time.time_ns() // PERIOD_NS + 1
    while time.time() < end:
        t = k * PERIOD_NS
        time.sleep(max(0.0, (t - time.time_ns()) / 1e9))
        for s, p in POSITIONS.items():
            p = np.array(p)
            az, el = azimuth_elevation(np.array(TARGET) - p)
            b = Bearing(s, t, p, float(az + SIGMA * rng.standard_normal()),
                        float(el + SIGMA * rng.standard_normal()), SIGMA, SIGMA)
            pubs[s].publish(bearing_to_msg(b))
        rclpy.spin_once(node, timeout_sec=0.0)
        k += 1
    node.destroy_node()
    rclpy.try_shutdown()


def run_fusion(qos, seconds):
    import rclpy
    from rclpy.parameter import Parameter

    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.serialization import deserialize_message

    from bearing_loc_ros import fusion_node
    from bearing_loc_ros.ros_conversions import time_to_ns

    def stamp_ns(msg):
        # The node subscribes raw (CDR bytes) or, in older builds, to messages.
        if isinstance(msg, (bytes, bytearray, memoryview)):
            msg = deserialize_message(bytes(msg), PoseWithCovarianceStamped)
        return time_to_ns(msg.header.stamp)

    delivered = {}
    fixes = []
    original = fusion_node.FusionNode._on_bearing

    def on_bearing(self, station, msg, info):
        t = stamp_ns(msg)
        delivered[t] = delivered.get(t, 0) + 1
        return original(self, station, msg, info)

    if len(inspect.signature(original).parameters) == 3:     # (self, station, msg): older
        def on_bearing(self, station, msg):  # noqa: F811 - the same for the older signature
            t = stamp_ns(msg)
            delivered[t] = delivered.get(t, 0) + 1
            return original(self, station, msg)

    def publish_epochs(self, epochs):
        for ep in epochs:
            if ep.ok:
                fixes.append([ep.stamp_ns, ep.position.tolist(), ep.covariance.tolist()])

    fusion_node.FusionNode._on_bearing = on_bearing
    fusion_node.FusionNode._publish_epochs = publish_epochs
    rclpy.init()
    node = fusion_node.FusionNode(namespace='/lossy', parameter_overrides=[
        Parameter('stations', value=list(POSITIONS)), Parameter('qos_reliability', value=qos),
        Parameter('estimator', value='mle'), Parameter('accuracy_map.enabled', value=False)])
    end = time.time() + seconds
    while time.time() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    diag = node.core.diagnostics(node.now_ns())
    lost = {d.name: {k: v for k, v in d.values.items()
                     if k.startswith(('lost.', 'dropped.', 'no_fix.', 'epochs'))}
            for d in diag}
    print(json.dumps({'delivered': delivered, 'fixes': fixes, 'lost': lost}))
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    role, qos, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
    {'stations': run_stations, 'fusion': run_fusion}[role](qos, seconds)
