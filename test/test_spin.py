"""spin.LeanExecutor: rclpy's single-threaded semantics, synchronous callbacks run directly.

Each test steps the executor with spin_once, as rclpy's executor tests do. A test node on a
second, plain SingleThreadedExecutor plays the other side (publisher, parameter client) so
that the executor under test sees no client of its own (with one it is rclpy's)."""

import time

from geometry_msgs.msg import PoseWithCovarianceStamped
import pytest
from rcl_interfaces.srv import GetParameters
import rclpy
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rclpy.task import Future

from bearing_loc_ros import ros_common
from bearing_loc_ros.spin import LeanExecutor

pytestmark = pytest.mark.ros

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
BEST_EFFORT = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)


class Pair:
    """``node`` on a LeanExecutor and ``peer`` on rclpy's executor, stepped in turn."""

    def __init__(self, ctx, name):
        self.node = rclpy.create_node(name, namespace='/lean_' + name, context=ctx)
        self.peer = rclpy.create_node(name + '_peer', namespace='/lean_' + name, context=ctx)
        self.ex = LeanExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.peer_ex = SingleThreadedExecutor(context=ctx)
        self.peer_ex.add_node(self.peer)
        self.tasks = 0
        make_handler = self.ex._make_handler

        def counting(*args):
            self.tasks += 1
            return make_handler(*args)
        self.ex._make_handler = counting      # rclpy Tasks made by the executor under test

    def spin(self, predicate, steps=200):
        for _ in range(steps):
            self.ex.spin_once(timeout_sec=0.02)
            self.peer_ex.spin_once(timeout_sec=0.0)
            if predicate():
                return True
        return False

    def close(self):
        for ex, node in ((self.ex, self.node), (self.peer_ex, self.peer)):
            ex.shutdown()
            node.destroy_node()


@pytest.fixture
def pair(ros, request):
    p = Pair(ros, request.node.name.replace('[', '_').replace(']', ''))
    yield p
    p.close()


def test_subscriptions_timers_and_services_run_directly(pair):
    typed, raw, ticks = [], [], []
    pair.node.create_subscription(PoseWithCovarianceStamped, 'typed', typed.append, RELIABLE)
    pair.node.create_subscription(PoseWithCovarianceStamped, 'raw',
                                  lambda data, info: raw.append((data, info)), RELIABLE,
                                  raw=True)
    pair.node.create_timer(0.01, lambda: ticks.append(1))
    pair.node.declare_parameter('answer', 42)
    pubs = [pair.peer.create_publisher(PoseWithCovarianceStamped, t, RELIABLE)
            for t in ('typed', 'raw')]
    assert pair.spin(lambda: all(p.get_subscription_count() for p in pubs))
    msg = PoseWithCovarianceStamped()
    msg.pose.pose.position.x = 1.5
    for p in pubs:
        p.publish(msg)
    assert pair.spin(lambda: typed and raw and len(ticks) >= 3)
    assert typed[0].pose.pose.position.x == 1.5
    data, info = raw[0]
    assert type(data) is bytes
    assert deserialize_message(data, PoseWithCovarianceStamped).pose.pose.position.x == 1.5
    assert info['publication_sequence_number'] >= 1
    # A parameter service of the node (asked by the peer's client).
    cli = pair.peer.create_client(GetParameters, '/lean_' + pair.node.get_name()
                                  + '/' + pair.node.get_name() + '/get_parameters')
    assert pair.spin(cli.service_is_ready)
    fut = cli.call_async(GetParameters.Request(names=['answer']))
    assert pair.spin(fut.done)
    assert fut.result().values[0].integer_value == 42
    assert pair.tasks == 0, 'plain callbacks must not go through rclpy Tasks'


def _awaiting(label, gate, order):
    """A coroutine callback: records ``label``, then what ``gate`` resolves to."""
    async def callback(msg):
        order.append(label)
        order.append(await gate)
    return callback


def test_coroutine_callback_runs_as_an_rclpy_task(pair):
    gate, order = Future(), []
    pair.node.create_subscription(PoseWithCovarianceStamped, 'co',
                                  _awaiting('start', gate, order), RELIABLE)
    pub = pair.peer.create_publisher(PoseWithCovarianceStamped, 'co', RELIABLE)
    assert pair.spin(lambda: pub.get_subscription_count())
    pub.publish(PoseWithCovarianceStamped())
    assert pair.spin(lambda: order == ['start'])
    assert pair.ex._tasks, 'the awaiting callback is a pending rclpy Task'
    gate.set_result('resumed')
    assert pair.spin(lambda: order == ['start', 'resumed'])
    assert pair.spin(lambda: not pair.ex._tasks)
    assert pair.tasks == 1


def test_pending_coroutine_holds_back_its_callback_group(pair):
    # As with rclpy's executor: while a coroutine callback of the default (mutually
    # exclusive) group awaits, a plain callback of that group ready in the same wake-up
    # waits for it.
    gate, order = Future(), []
    pair.node.create_subscription(PoseWithCovarianceStamped, 'a',
                                  _awaiting('first', gate, order), RELIABLE)
    pair.node.create_subscription(PoseWithCovarianceStamped, 'b',
                                  lambda m: order.append('second'), RELIABLE)
    pubs = [pair.peer.create_publisher(PoseWithCovarianceStamped, t, RELIABLE)
            for t in ('a', 'b')]
    assert pair.spin(lambda: all(p.get_subscription_count() for p in pubs))
    for p in pubs:
        p.publish(PoseWithCovarianceStamped())
    time.sleep(0.3)         # both delivered before the executor wakes: one wake-up
    assert pair.spin(lambda: 'first' in order)
    pair.spin(lambda: False, steps=10)
    assert order == ['first']
    gate.set_result('resumed')
    assert pair.spin(lambda: len(order) == 3)
    assert order == ['first', 'resumed', 'second']


def test_middleware_event_handlers_still_fire(pair):
    # A waitable (the subscription's incompatible-QoS event) in the executor's wait set.
    events = []
    pair.node.create_subscription(
        PoseWithCovarianceStamped, 'qos', lambda m: None, RELIABLE,
        event_callbacks=SubscriptionEventCallbacks(incompatible_qos=events.append))
    pair.peer.create_publisher(PoseWithCovarianceStamped, 'qos', BEST_EFFORT)
    assert pair.spin(lambda: events)
    assert events[0].total_count == 1


def test_callback_exception_propagates_from_spin_once(pair):
    def boom():
        raise ValueError('boom in a timer')
    pair.node.create_timer(0.001, boom)
    with pytest.raises(ValueError, match='boom in a timer'):
        pair.spin(lambda: False, steps=50)


def _own_context(name):
    """A node with a publisher and a subscription of topic 'x' on a LeanExecutor of its
    own context, discovery done: (ctx, node, executor, publisher, subscription, received)."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(name, context=ctx)
    got = []
    pub = node.create_publisher(PoseWithCovarianceStamped, 'x', RELIABLE)
    sub = node.create_subscription(PoseWithCovarianceStamped, 'x', got.append, RELIABLE)
    ex = LeanExecutor(context=ctx)
    ex.add_node(node)
    for _ in range(100):
        if pub.get_subscription_count():
            break
        ex.spin_once(timeout_sec=0.02)
    return ctx, node, ex, pub, sub, got


def _ready_together(node, pub, timer_callback):
    """A message pending on 'x' and a timer due, both before the next wait: the executor
    sees them in one wake-up, and runs the timer first."""
    pub.publish(PoseWithCovarianceStamped())
    time.sleep(0.2)
    node.create_timer(0.001, timer_callback)
    time.sleep(0.05)


def test_entity_destroyed_by_an_earlier_callback_is_skipped():
    # The timer destroys the subscription whose message is ready in the same wake-up: the
    # subscription is skipped (rclpy's _take_* skip it too), the spin goes on.
    ctx, node, ex, pub, sub, got = _own_context('lean_destroyed')
    destroyed = []

    def destroy():
        if not destroyed:
            destroyed.append(node.destroy_subscription(sub))
    try:
        _ready_together(node, pub, destroy)
        for _ in range(5):
            ex.spin_once(timeout_sec=0.05)
        assert destroyed == [True] and got == []
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_no_callback_of_the_batch_runs_after_the_context_is_shut_down():
    # The timer shuts the context down while a subscription is ready in the same wake-up:
    # its callback must not run (it would publish on a dead context), and the spin ends
    # with ExternalShutdownException, as rclpy's does.
    ctx, node, ex, pub, _, got = _own_context('lean_shutdown_batch')
    try:
        _ready_together(node, pub, lambda: ctx.try_shutdown())
        with pytest.raises(ExternalShutdownException):
            for _ in range(20):
                ex.spin_once(timeout_sec=0.05)
        assert got == []
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_context_shutdown_ends_the_spin():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('lean_shutdown', context=ctx)
    ex = LeanExecutor(context=ctx)
    ex.add_node(node)
    node.create_timer(0.01, lambda: rclpy.shutdown(context=ctx))
    try:
        with pytest.raises(ExternalShutdownException):
            for _ in range(100):
                ex.spin_once(timeout_sec=0.05)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


class _Failing(Node):
    def __init__(self):
        super().__init__('lean_failing')
        self.create_timer(0.01, self._boom)

    def _boom(self):
        raise ValueError('boom in a callback')


def test_run_node_with_the_lean_executor_reports_internal_errors(capsys):
    assert ros_common.run_node(_Failing, args=[], executor=LeanExecutor) == \
        ros_common.INTERNAL_ERROR
    err = capsys.readouterr().err
    assert 'internal error' in err and 'boom in a callback' in err


class _Done(Node):
    def __init__(self):
        super().__init__('spin_test_done')
        self.create_timer(0.01, self._finish)

    def _finish(self):
        raise ros_common.Finished('done')


@pytest.mark.parametrize('executor', [None, LeanExecutor])
def test_run_node_ends_normally_when_a_callback_is_finished(executor, capsys):
    # A node that is done raises Finished from its callback (the simulator's exit_when_done):
    # exit code 0, no error printed, on rclpy's executor and on the lean one.
    assert ros_common.run_node(_Done, args=[], executor=executor) == 0
    assert 'error' not in capsys.readouterr().err
