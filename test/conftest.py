"""Session-wide test set-up: an own ROS_DOMAIN_ID, loopback-only discovery, ament index."""
import os
import sys

import pytest

# Each test session gets its own DDS domain (0..101 are safe on Linux) so parallel runs on
# one machine never see each other's nodes; discovery stays on loopback.
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
os.environ.setdefault('MPLBACKEND', 'Agg')
sys.path.insert(0, os.path.dirname(__file__))


@pytest.fixture(scope='session', autouse=True)
def compiled_numerics():
    """The one-fix numerics compiled into numba's cache once, before any test starts a node
    process (which would otherwise compile them itself, several at a time)."""
    from bearing_loc_ros.core.warmup import warm_up
    warm_up()


@pytest.fixture(scope='module')
def ros():
    """An rclpy context of its own for the test module (in-process node tests)."""
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def harness(ros):
    """Factory of in-process fusion-node harnesses (test_fusion_node.Harness), all closed."""
    from test_fusion_node import Harness
    made = []

    def make(**kw):
        h = Harness(ros, **kw)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()
