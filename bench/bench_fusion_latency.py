"""Fusion latency and CPU benchmark (prints figures; no assertions).

For N = 3, 10 and 50 stations at 10 Hz, a ``fusion_node`` process (event trigger, default
estimator, system clock) receives N bearings per epoch from this process over DDS (loopback).
Reported per N:

* end-to-end latency: from the publication of the bearing that completes an epoch (the last
  of the N) to the reception of its fix here, wall clock (two DDS hops + the node's
  conversion, alignment, estimation, gating and publication). The event trigger has no
  configured wait, so nothing needs subtracting; a timer trigger would add max_latency plus
  up to one tick period.
* the fusion node's CPU use over the measurement window, from /proc/<pid>/stat
  (utime + stime), in % of one core;
* the core alone: time of FusionCore.add_bearing for the epoch-completing bearing (alignment,
  estimator and outlier gate; no ROS), median and p99.

Each run is paired with a run of the same harness against a trivial rclpy node that
subscribes to the N topics and republishes the epoch-completing bearing on /fix: the
rclpy + DDS floor that any Python node pays. The pair runs back to back and its ratio
(fusion e2e median / echo e2e median) is printed; ``--repeat`` pairs per N give the spread
on a shared machine. ``--baseline`` runs the echo node only.

Run: ``.venv/bin/python bench/bench_fusion_latency.py [--seconds 10] [--estimator mle]
[--stations 10,50] [--repeat 3] [--baseline]``.
"""

import argparse
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from bearing_loc_ros.core.bearings import Bearing  # noqa: E402
from bearing_loc_ros.core.conventions import azimuth_elevation  # noqa: E402
from bearing_loc_ros.core.fusion import FusionConfig, FusionCore  # noqa: E402
from bearing_loc_ros.processes import interrupt  # noqa: E402

RATE = 10.0
SIGMA = 2e-3
TARGET = np.array([1500.0, -800.0, 1200.0])


def station_positions(n):
    """n stations on a 10 km circle, heights 0-50 m."""
    a = 2.0 * np.pi * np.arange(n) / n
    return np.stack([1e4 * np.cos(a), 1e4 * np.sin(a), 50.0 * (np.arange(n) % 2)], axis=1)


def make_bearings(n, stamp_ns, rng):
    pos = station_positions(n)
    az, el = azimuth_elevation(TARGET - pos)
    az = az + SIGMA * rng.standard_normal(n)
    el = el + SIGMA * rng.standard_normal(n)
    return [Bearing(f's{i}', stamp_ns, pos[i], float(az[i]), float(el[i]), SIGMA, SIGMA)
            for i in range(n)]


ECHO_NODE = """
import sys, rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
rclpy.init(args=sys.argv)
node = rclpy.create_node('fusion')
n = len(node.declare_parameter('stations', ['s0']).value)
pub = node.create_publisher(PoseWithCovarianceStamped, 'fix', 10)
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
for i in range(n):
    node.create_subscription(PoseWithCovarianceStamped, f's{i}/bearing',
                             pub.publish if i == n - 1 else (lambda m: None), qos)
try:
    rclpy.spin(node)
except KeyboardInterrupt:
    pass
"""


def cpu_seconds(pid):
    """utime + stime of a process, seconds (/proc/<pid>/stat fields 14 and 15)."""
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def core_only(n, estimator, epochs=200):
    """Median and p99 (ms) of the core's epoch-completing add_bearing, no ROS."""
    rng = np.random.default_rng(n)
    core = FusionCore(FusionConfig(estimator=estimator), stations=[f's{i}' for i in range(n)])
    times = []
    for k in range(epochs):
        t = (100 + k) * 100_000_000
        bs = make_bearings(n, t, rng)
        for b in bs[:-1]:
            core.add_bearing(b, t)
        t0 = time.perf_counter()
        out = core.add_bearing(bs[-1], t)
        times.append(time.perf_counter() - t0)
        assert out and out[0].ok, out
    ms = np.array(times[20:]) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 99))


def over_dds(n, seconds, estimator, baseline=False):
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from bearing_loc_ros.ros_conversions import bearing_to_msg, fix_from_msg

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    stations = '[' + ','.join(f'"s{i}"' for i in range(n)) + ']'
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    if baseline:
        cmd = [sys.executable, '-c', ECHO_NODE, '--ros-args', '-p', f'stations:={stations}']
    else:
        cmd = [sys.executable, '-m', 'bearing_loc_ros.fusion_node', '--ros-args',
               '-p', f'stations:={stations}', '-p', f'estimator:={estimator}',
               '-p', 'publish_markers:=false', '--log-level', 'warn']
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                            start_new_session=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, args=[])
    node = rclpy.create_node('bench_fusion', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    received = {}
    node.create_subscription(PoseWithCovarianceStamped, '/fix',
                             lambda m: received.setdefault(fix_from_msg(m)[0],
                                                           time.perf_counter()), qos)
    pubs = [node.create_publisher(PoseWithCovarianceStamped, f'/s{i}/bearing', qos)
            for i in range(n)]
    rng = np.random.default_rng(0)
    try:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and not (
                node.count_publishers('/fix') > 0
                and all(p.get_subscription_count() > 0 for p in pubs)):
            ex.spin_once(timeout_sec=0.05)
        warmup, total = 2.0, 2.0 + seconds
        sent = {}
        period = 1.0 / RATE
        t_start = time.monotonic()
        k = 0
        cpu0 = wall0 = None
        while True:
            due = t_start + k * period
            while time.monotonic() < due:
                ex.spin_once(timeout_sec=max(0.0, min(0.005, due - time.monotonic())))
            if k * period >= total:
                break
            if cpu0 is None and k * period >= warmup:
                cpu0, wall0 = cpu_seconds(proc.pid), time.monotonic()
            stamp = time.time_ns()
            msgs = [bearing_to_msg(b) for b in make_bearings(n, stamp, rng)]
            for p, m in zip(pubs[:-1], msgs[:-1]):
                p.publish(m)
            t_last = time.perf_counter()
            pubs[-1].publish(msgs[-1])
            if k * period >= warmup:
                sent[stamp] = t_last
            k += 1
        cpu = (cpu_seconds(proc.pid) - cpu0) / (time.monotonic() - wall0)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.02)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        interrupt(proc, 5)
    lat = np.array([received[s] - t for s, t in sent.items() if s in received]) * 1e3
    return lat, len(sent), cpu


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=10.0, help='measurement window per run')
    ap.add_argument('--estimator', default='mle')
    ap.add_argument('--stations', default='3,10,50')
    ap.add_argument('--repeat', type=int, default=1,
                    help='echo/fusion pairs per N (interleaved; the ratio is per pair)')
    ap.add_argument('--baseline', action='store_true',
                    help='only the trivial echo node (the floor), no fusion_node')
    args = ap.parse_args()
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    what = ('trivial echo node only (rclpy + DDS floor)' if args.baseline else
            f'fusion_node (estimator {args.estimator}, event trigger) next to the trivial '
            'echo node (rclpy + DDS floor), run in pairs')
    print(f'latency at {RATE:g} Hz epochs: {what}; {args.seconds:g} s per run, '
          f'{os.cpu_count()} CPUs, ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]}')
    print('| stations | run | fixes/epochs | fusion e2e median (ms) | fusion e2e p99 (ms) '
          '| echo e2e median (ms) | ratio | fusion CPU (% core) | echo CPU (% core) '
          '| core median (ms) | core p99 (ms) |')
    print('|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|')
    nan = float('nan')
    for n in (int(s) for s in args.stations.split(',')):
        c_med, c_p99 = (nan, nan) if args.baseline else core_only(n, args.estimator)
        ratios = []
        for r in range(args.repeat):
            e_lat, _, e_cpu = over_dds(n, args.seconds, args.estimator, baseline=True)
            e_med = np.median(e_lat) if len(e_lat) else nan
            if args.baseline:
                lat, sent, cpu = e_lat, len(e_lat), nan
            else:
                lat, sent, cpu = over_dds(n, args.seconds, args.estimator)
            med = np.median(lat) if len(lat) else nan
            p99 = np.percentile(lat, 99) if len(lat) else nan
            ratios.append(med / e_med)
            print(f'| {n} | {r + 1} | {len(lat)}/{sent} | {med:.2f} | {p99:.2f} | {e_med:.2f} '
                  f'| {med / e_med:.2f} | {100 * cpu:.1f} | {100 * e_cpu:.1f} | {c_med:.2f} '
                  f'| {c_p99:.2f} |', flush=True)
        if args.repeat > 1 and not args.baseline:
            print(f'| {n} | all | | | | | {np.median(ratios):.2f} [{min(ratios):.2f}-'
                  f'{max(ratios):.2f}] | | | | |', flush=True)


if __name__ == '__main__':
    main()
