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
  estimator and outlier gate; no ROS; the station-trust update that the node runs after
  publishing, FusionCore.settle, not included), median and p99.

Each run measures, in the same harness, a trivial rclpy node that subscribes to the N
topics (typed messages, rclpy's default subscription) and republishes the epoch-completing
bearing on its fix topic: the rclpy + DDS floor that a Python node pays. Both nodes run
at once (namespaces /echo and /fusion) and the epochs go to one of them at a time, in
alternating blocks of ``--block`` seconds, so a change of the shared machine's load hits
both alike; the ratio (fusion e2e median / echo e2e median) is printed per run, and
``--repeat`` runs per N give its spread. ``--seconds`` is the measurement time per node.
``--baseline`` runs the echo node only. ``--lean-echo`` adds a third node, the echo with
raw subscriptions and no middleware-event handlers in the wait set (as the fusion node
subscribes): the lowest floor an rclpy node reaches, and the fusion's ratio to it.

Run: ``.venv/bin/python bench/bench_fusion_latency.py [--seconds 10] [--estimator mle]
[--stations 10,50] [--repeat 3] [--block 1] [--lean-echo] [--baseline]``.
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
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import QoSProfile, ReliabilityPolicy
rclpy.init(args=sys.argv)
node = rclpy.create_node('fusion')
n = len(node.declare_parameter('stations', ['s0']).value)
lean = node.declare_parameter('lean', False).value
pub = node.create_publisher(PoseWithCovarianceStamped, 'fix', 10)
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
events = SubscriptionEventCallbacks(use_default_callbacks=False) if lean else None
for i in range(n):
    node.create_subscription(PoseWithCovarianceStamped, f's{i}/bearing',
                             pub.publish if i == n - 1 else (lambda m: None), qos,
                             event_callbacks=events, raw=lean)
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
        core.settle()      # as the node does once the fix is published
        assert out and out[0].ok, out
    ms = np.array(times[20:]) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 99))


def start_node(kind, n, estimator):
    """Start the ``kind`` node in namespace /<kind>: 'echo', 'lean' (the echo node with raw
    subscriptions and no middleware-event handlers, as the fusion node subscribes) or
    'fusion'."""
    stations = '[' + ','.join(f'"s{i}"' for i in range(n)) + ']'
    args = ['--ros-args', '-r', f'__ns:=/{kind}', '-p', f'stations:={stations}']
    if kind in ('echo', 'lean'):
        cmd = [sys.executable, '-c', ECHO_NODE] + args + ['-p', f'lean:={kind == "lean"}']
    else:
        cmd = [sys.executable, '-m', 'bearing_loc_ros.fusion_node'] + args + [
            '-p', f'estimator:={estimator}', '-p', 'publish_markers:=false',
            '--log-level', 'warn']
    return subprocess.Popen(cmd, env=dict(os.environ, PYTHONUNBUFFERED='1'),
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                            start_new_session=True)


def over_dds(n, seconds, estimator, kinds=('echo', 'fusion'), block=1.0):
    """Latencies (ms) and CPU (fraction of a core) of each node in ``kinds``, run at once.

    Every node runs during the whole measurement, in its own namespace; the epochs go to
    one node at a time, in alternating blocks of ``block`` seconds, so a change of the
    machine's load hits every node alike (back-to-back runs of several seconds each differed
    by up to 2x on a shared machine). A node's CPU is counted over its own blocks only.
    Returns {kind: (latencies ms (array), epochs sent, cpu)}.
    """
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from bearing_loc_ros.ros_conversions import bearing_to_msg, fix_from_msg

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    procs = {kind: start_node(kind, n, estimator) for kind in kinds}
    ctx = rclpy.Context()
    rclpy.init(context=ctx, args=[])
    node = rclpy.create_node('bench_fusion', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    received = {kind: {} for kind in kinds}
    for kind in kinds:
        node.create_subscription(
            PoseWithCovarianceStamped, f'/{kind}/fix',
            lambda m, got=received[kind]: got.setdefault(fix_from_msg(m)[0],
                                                         time.perf_counter()), qos)
    pubs = {kind: [node.create_publisher(PoseWithCovarianceStamped, f'/{kind}/s{i}/bearing',
                                         qos) for i in range(n)] for kind in kinds}
    rng = np.random.default_rng(0)
    sent = {kind: {} for kind in kinds}
    cpu = dict.fromkeys(kinds, 0.0)
    active = dict.fromkeys(kinds, 0.0)
    try:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and not all(
                node.count_publishers(f'/{kind}/fix') > 0
                and all(p.get_subscription_count() > 0 for p in pubs[kind])
                for kind in kinds):
            ex.spin_once(timeout_sec=0.05)
        period = 1.0 / RATE
        per_block = max(1, int(round(block * RATE)))
        warmup = 2 * per_block                       # one block per node, not counted
        total = warmup + len(kinds) * per_block * max(1, int(round(seconds / block)))
        t_start = time.monotonic()
        mark = None
        for k in range(total + 1):
            due = t_start + k * period
            while time.monotonic() < due:
                ex.spin_once(timeout_sec=max(0.0, min(0.005, due - time.monotonic())))
            if k % per_block == 0:               # block boundary: CPU of the last block
                if mark is not None:
                    kind, c0, w0 = mark
                    cpu[kind] += cpu_seconds(procs[kind].pid) - c0
                    active[kind] += time.monotonic() - w0
                    mark = None
                if k >= total:
                    break
                kind = kinds[(k // per_block) % len(kinds)]
                if k >= warmup:
                    mark = (kind, cpu_seconds(procs[kind].pid), time.monotonic())
            kind = kinds[(k // per_block) % len(kinds)]
            stamp = time.time_ns()
            msgs = [bearing_to_msg(b) for b in make_bearings(n, stamp, rng)]
            for p, m in zip(pubs[kind][:-1], msgs[:-1]):
                p.publish(m)
            t_last = time.perf_counter()
            pubs[kind][-1].publish(msgs[-1])
            if k >= warmup:
                sent[kind][stamp] = t_last
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.02)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        for proc in procs.values():
            interrupt(proc, 5)
    out = {}
    for kind in kinds:
        got = received[kind]
        lat = np.array([got[s] - t for s, t in sent[kind].items() if s in got]) * 1e3
        out[kind] = (lat, len(sent[kind]), cpu[kind] / active[kind] if active[kind] else
                     float('nan'))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=10.0, help='measurement window per run')
    ap.add_argument('--estimator', default='mle')
    ap.add_argument('--stations', default='3,10,50')
    ap.add_argument('--repeat', type=int, default=1,
                    help='echo/fusion runs per N (the ratio is per run)')
    ap.add_argument('--block', type=float, default=1.0,
                    help='seconds of epochs sent to one node before switching to the other')
    ap.add_argument('--lean-echo', action='store_true',
                    help='also run the echo node with raw subscriptions and no middleware-'
                    'event handlers (the leanest rclpy floor) and print the ratio to it')
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
    lean = (' lean echo e2e median (ms) | ratio to lean | lean echo CPU (% core) |'
            if args.lean_echo else '')
    print('| stations | run | fixes/epochs | fusion e2e median (ms) | fusion e2e p99 (ms) '
          '| echo e2e median (ms) | ratio | fusion CPU (% core) | echo CPU (% core) '
          f'| core median (ms) | core p99 (ms) |{lean}')
    print('|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|'
          + ('---:|---:|---:|' if args.lean_echo else ''))
    nan = float('nan')
    kinds = ('echo',) if args.baseline else ('echo', 'fusion')
    if args.lean_echo:
        kinds += ('lean',)
    for n in (int(s) for s in args.stations.split(',')):
        c_med, c_p99 = (nan, nan) if args.baseline else core_only(n, args.estimator)
        ratios = []
        for r in range(args.repeat):
            res = over_dds(n, args.seconds, args.estimator, kinds, args.block)
            e_lat, e_sent, e_cpu = res['echo']
            e_med = np.median(e_lat) if len(e_lat) else nan
            lat, sent, cpu = res.get('fusion', (e_lat, e_sent, nan))
            med = np.median(lat) if len(lat) else nan
            p99 = np.percentile(lat, 99) if len(lat) else nan
            ratios.append(med / e_med)
            lean = ''
            if args.lean_echo:
                l_lat, _, l_cpu = res['lean']
                l_med = np.median(l_lat) if len(l_lat) else nan
                lean = f' {l_med:.2f} | {med / l_med:.2f} | {100 * l_cpu:.1f} |'
            print(f'| {n} | {r + 1} | {len(lat)}/{sent} | {med:.2f} | {p99:.2f} | {e_med:.2f} '
                  f'| {med / e_med:.2f} | {100 * cpu:.1f} | {100 * e_cpu:.1f} | {c_med:.2f} '
                  f'| {c_p99:.2f} |{lean}', flush=True)
        if args.repeat > 1 and not args.baseline:
            print(f'| {n} | all | | | | | {np.median(ratios):.2f} [{min(ratios):.2f}-'
                  f'{max(ratios):.2f}] | | | | |', flush=True)


if __name__ == '__main__':
    main()
