"""A live station node (in process) under a burst of hostile UDP datagrams.

Every datagram sent is accounted for: read by the node (then published or rejected by
reason) or dropped by the kernel because the node was not reading (``udp_dropped_by_kernel``
in the diagnostics, which turn WARN and say so). The node's receive buffer is shrunk to 4 KiB
so the burst overflows it on any host, whatever its default buffer size. The burst holds the
single-datagram repros (a 400-digit azimuth, ``t`` = 1e200000, an exponent beyond decimal's
range) that once killed or froze the node, valid readings, random bytes and mutated
readings from a fixed seed.
"""

import math
import random
import socket

from diagnostic_msgs.msg import DiagnosticStatus
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from ros_helpers import free_udp_port, spin_until

from bearing_loc_ros.station_node import StationNode

pytestmark = pytest.mark.ros

VALID = b'{"t": 1700000000.5, "azimuth_deg": 12.5, "sigma_deg": 1.5}'
REPROS = (b'{"t": 1700000000, "azimuth_deg": 1' + b'0' * 400 + b'}',
          b'{"t": 1e200000, "azimuth_deg": 1}', b'{"t": 1e999990, "azimuth_deg": 1}',
          b'{"t": 1700000000, "azimuth_deg": 1e300}',
          # beyond what decimal holds: Decimal() raised InvalidOperation, exit code 70
          b'{"t": 1700000000, "azimuth_deg": 1e1000000000000000000}',
          b'{"t": 1700000000, "azimuth_deg": 2, "x": 1e1000000000000000000}')


def burst(n, seed=13):
    """n datagrams: repros, valid readings, random bytes and mutated readings."""
    rng = random.Random(seed)
    out = list(REPROS)
    while len(out) < n:
        kind = rng.randrange(3)
        if kind == 0:
            out.append(VALID)
        elif kind == 1:
            out.append(rng.randbytes(rng.randrange(1, 200)))
        else:
            i = rng.randrange(len(VALID))
            out.append(VALID[:i] + rng.randbytes(rng.randrange(1, 8)) + VALID[i + 1:])
    return out


@pytest.fixture
def station():
    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    port = free_udp_port()
    node = StationNode(context=context, namespace='/fuzz_udp', parameter_overrides=[
        Parameter('position', value=[0.0, 0.0, 0.0]), Parameter('udp_port', value=port),
        Parameter('diagnostics_period_s', value=3600.0)])
    executor.add_node(node)
    try:
        yield node, executor, port
    finally:
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown()
        rclpy.shutdown(context=context)


def test_every_datagram_is_counted_or_reported_dropped(station):
    node, executor, port = station
    node._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sent = burst(1000)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for data in sent:  # the node does not read meanwhile: the kernel queue overflows
            tx.sendto(data, ('127.0.0.1', port))

    def drained():
        before = node.received['udp']
        executor.spin_once(timeout_sec=0.05)
        executor.spin_once(timeout_sec=0.05)
        return node.received['udp'] == before and before > 0
    assert spin_until(executor, drained, 10.0)

    status = node.diagnostic_status()
    values = {kv.key: kv.value for kv in status.values}
    read, dropped = node.received['udp'], int(values['udp_dropped_by_kernel'])
    assert dropped > 0 and read + dropped == len(sent)
    assert node.published + sum(node.rejected.values()) == read  # each read one counted
    assert int(values['published']) == node.published
    assert status.level == DiagnosticStatus.WARN
    assert f'{dropped} UDP datagram(s) dropped by the kernel' in status.message
    # Nothing new since: the drop count stays, the warning goes.
    again = node.diagnostic_status()
    values = {kv.key: kv.value for kv in again.values}
    assert int(values['udp_dropped_by_kernel']) == dropped
    assert again.level == DiagnosticStatus.OK and 'dropped' not in again.message


def test_repros_are_rejected_by_reason_and_the_node_keeps_publishing(station):
    node, executor, port = station
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for data in REPROS + (VALID,):
            tx.sendto(data, ('127.0.0.1', port))
    assert spin_until(executor, lambda: node.received['udp'] == len(REPROS) + 1, 10.0)
    assert dict(node.rejected) == {'bad_azimuth': 3, 'bad_t': 2}
    assert node.published == 2 and node.last_stamp_ns == 1_700_000_000_500_000_000
    values = {kv.key: kv.value for kv in node.diagnostic_status().values}
    assert values['udp_dropped_by_kernel'] == '0'
    assert math.isfinite(float(values['last_stamp_s']))
