"""Helpers for tests that start nodes as separate processes or spin nodes in-process.

* :func:`start_node` starts ``python -m <module> --ros-args ...`` with the session's
  ROS_DOMAIN_ID (set in conftest) and returns a :class:`NodeProcess`.
* :class:`NodeProcess` stops its child with SIGINT, waits with a timeout, escalates to
  SIGTERM then SIGKILL, and always reaps it. Use it as a context manager.
* :func:`free_udp_port` gives a loopback UDP port outside the kernel's ephemeral range, so
  no socket another process opens in the meantime (DDS, a probe) can take it first.
* :func:`spin_until` spins an executor until a predicate holds or a timeout passes.
* :class:`Probe` is a node in a fresh rclpy context with its own executor, torn down by
  :meth:`Probe.close`.
* :data:`GHOST_PUBLISHERS` is a script holding N empty ``ghost_<k>/bearing`` publishers.
* :func:`seed000_variant` writes the seed000 scenario with another rate and duration;
  :func:`static3_bags` simulates the static3 scenario into a bag of every storage.
"""
import os
import random
import socket
import sys
import time

from bearing_loc_ros.processes import ChildProcess

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: ``python -c GHOST_PUBLISHERS NAMESPACE N``: N empty publishers on ``ghost_<k>/bearing``
#: under NAMESPACE; prints ``ready`` and holds them until a line arrives on stdin.
GHOST_PUBLISHERS = '''
import sys, rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
rclpy.init()
node = rclpy.create_node('ghosts', namespace=sys.argv[1])
pubs = [node.create_publisher(PoseWithCovarianceStamped, f'ghost_{k}/bearing', 10)
        for k in range(int(sys.argv[2]))]
print('ready', flush=True)
sys.stdin.readline()
'''


class NodeProcess(ChildProcess):
    """A child process running a node, started in the repository root."""

    def __init__(self, args, env=None):
        super().__init__(args, env=env, cwd=REPO)


def node_env(**extra):
    """The environment for a node child: inherits the session's ROS settings."""
    env = dict(os.environ)
    env['PYTHONUNBUFFERED'] = '1'
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    env.update({k: str(v) for k, v in extra.items()})
    return env


def start_node(module, ros_args=(), args=(), env=None):
    """Start ``python -m module [args] --ros-args [ros_args]`` as a NodeProcess."""
    cmd = [sys.executable, '-m', module, *args]
    if ros_args:
        cmd += ['--ros-args', *ros_args]
    return NodeProcess(cmd, env=env or node_env())


def free_udp_port():
    """A free loopback UDP port the kernel never hands out on its own.

    A port found by binding port 0 lies in the ephemeral range: between the probe and the
    node's own bind, any socket opened meanwhile (a DDS participant, another test) may get
    it. Ports above ``ip_local_port_range`` are only ever taken by explicit binds; DDS's
    well-known ports (7400 + 250 × domain + …) stay below 61,000 for the domain IDs the
    tests use (≤ 209).
    """
    try:
        with open('/proc/sys/net/ipv4/ip_local_port_range') as f:
            high = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        high = 60999
    first = min(max(high + 1, 61000), 65000)
    for port in random.sample(range(first, 65400), 200):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(('127.0.0.1', port))
            except OSError:
                continue
            return port
    raise RuntimeError('no free UDP port above the ephemeral range')


def spin_until(executor, predicate, timeout):
    """Spin ``executor`` in 50 ms steps until ``predicate()`` is true; return its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
        value = predicate()
        if value:
            return value
    return predicate()


class Probe:
    """A node ``name`` in a fresh rclpy context, added to its own single-threaded executor.

    ``node``, ``executor`` and ``context`` are public; :meth:`close` (also on leaving a
    ``with`` block) removes and destroys the extra ``nodes``, shuts the executor down,
    destroys the probe node and shuts the context down.
    """

    def __init__(self, name='probe'):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor.add_node(self.node)

    def close(self, nodes=()):
        import rclpy
        for node in nodes:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def seed000_variant(tmp_path, name, rate, duration):
    """config/scenarios/seed000.yaml with every station at ``rate`` Hz and ``duration`` s,
    written to ``tmp_path / name``; returns its path (str)."""
    import yaml
    with open(os.path.join(REPO, 'config/scenarios/seed000.yaml'), encoding='utf-8') as f:
        data = yaml.safe_load(f)
    data['station_defaults']['rate'] = rate
    data['duration'] = duration
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return str(path)


def static3_bags(root, seed):
    """config/scenarios/static3.yaml simulated with ``seed`` into one bag per storage,
    ``root / 'static3_<storage>'``; returns (scenario, {storage: path})."""
    from bearing_loc_ros import bagio
    from bearing_loc_ros.cli.bag import simulate_bag
    from bearing_loc_ros.core.simulation import load_scenario
    scenario = load_scenario(os.path.join(REPO, 'config', 'scenarios', 'static3.yaml'))
    out = {}
    for storage in bagio.STORAGES:
        out[storage] = root / f'static3_{storage}'
        simulate_bag(scenario, out[storage], seed=seed, storage=storage)
    return scenario, out
