"""Soak: a fusion node fed by many stations for a long time; RSS growth and epochs fixed.

    .venv/bin/python bench/soak_fusion.py [--stations 50] [--rate 10] [--duration 900]

Starts a fusion node (``python -m bearing_loc_ros.fusion_node``, default QoS and event
trigger, estimator ls) in namespace /soak and a publisher process with N stations observing
a fixed target together at ``rate`` Hz (noisy bearings, σ = 3 mrad), both on loopback with
their own ROS_DOMAIN_ID. The fusion node's RSS (/proc/<pid>/status VmRSS) is sampled after
a warm-up and every minute; the fusion /diagnostics give its epochs and fixes. Prints the
RSS growth from the first sample after the warm-up to the end, and the fraction of the
observation cycles published after the warm-up that were fixed (and fixes / epochs).
"""
import argparse
import os
import subprocess
import sys
import time

import numpy as np

TARGET = np.array([2500.0, 3000.0, 800.0])
SIGMA = 3e-3


def station_positions(n):
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return {f's{k + 1}': [5000.0 * np.cos(v), 5000.0 * np.sin(v), 10.0 * (k % 5)]
            for k, v in enumerate(a)}


def run_publisher(n, rate, seconds):
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from bearing_loc_ros.core.bearings import Bearing
    from bearing_loc_ros.core.conventions import azimuth_elevation
    from bearing_loc_ros.ros_common import keep_last_qos
    from bearing_loc_ros.ros_conversions import bearing_to_msg

    # A paced synthetic-station loop like test/lossy_link_peer.py's, kept here on purpose: a
    # benchmark stays a self-contained script with its own station count and rate.
    rclpy.init()
    node = rclpy.create_node('soak_stations', namespace='/soak')
    pos = station_positions(n)
    pubs = {s: node.create_publisher(PoseWithCovarianceStamped, f'{s}/bearing',
                                     keep_last_qos(10, 'best_effort')) for s in pos}
    rng = np.random.default_rng(3)
    period = int(1e9 / rate)
    end = time.time() + seconds
    k = time.time_ns() // period + 1
    while time.time() < end:
        t = k * period
        time.sleep(max(0.0, (t - time.time_ns()) / 1e9))
        for s, p in pos.items():
            p = np.array(p)
            az, el = azimuth_elevation(TARGET - p)
            pubs[s].publish(bearing_to_msg(Bearing(
                s, t, p, float(az + SIGMA * rng.standard_normal()),
                float(el + SIGMA * rng.standard_normal()), SIGMA, SIGMA)))
        k += 1
    node.destroy_node()
    rclpy.try_shutdown()


def rss_kb(pid):
    with open(f'/proc/{pid}/status') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1])
    return None


def bench_env(base, span):
    """Environment of a bench run: its own ROS domain (``base`` + pid mod ``span``),
    discovery on loopback, unbuffered output, the venv as the ament prefix."""
    return dict(os.environ, ROS_DOMAIN_ID=str(base + os.getpid() % span),
                ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
                AMENT_PREFIX_PATH=os.environ.get('AMENT_PREFIX_PATH', sys.prefix))


def start_publisher(env, stations, rate, duration):
    """Start this script's paced synthetic stations (role ``publisher``) as a child."""
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    pub = subprocess.Popen([sys.executable, os.path.abspath(__file__), '--role', 'publisher',
                            '--stations', str(stations), '--rate', str(rate),
                            '--duration', str(duration)], cwd=repo, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # The measuring node of the calling process joins the same domain.
    os.environ.update(ROS_DOMAIN_ID=env['ROS_DOMAIN_ID'],
                      ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return pub


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--stations', type=int, default=50)
    ap.add_argument('--rate', type=float, default=10.0)
    ap.add_argument('--duration', type=float, default=900.0, help='seconds (default 900)')
    ap.add_argument('--warm-up', type=float, default=20.0)
    ap.add_argument('--role', default='main', help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.role == 'publisher':
        return run_publisher(a.stations, a.rate, a.duration)
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = bench_env(120, 40)
    names = list(station_positions(a.stations))
    fusion = subprocess.Popen(
        [sys.executable, '-m', 'bearing_loc_ros.fusion_node', '--ros-args', '-r', '__ns:=/soak',
         '-p', f'stations:=[{",".join(names)}]', '-p', 'estimator:=ls',
         '-p', 'accuracy_map.enabled:=false', '-p', 'diagnostics_period:=1.0',
         '-p', f'buffer_size:={max(50, int(2 * a.rate))}'],
        cwd=repo, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    total = a.duration + a.warm_up + 5
    pub = start_publisher(env, a.stations, a.rate, total)
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    from bearing_loc_ros.processes import interrupt
    rclpy.init()
    node = rclpy.create_node('soak_probe')
    last = {}

    def on_diag(msg):
        for s in msg.status:
            if s.name.endswith(': fusion'):
                last.update({kv.key: kv.value for kv in s.values})
                # The counters hold at this stamp (node clock), not at the reception time.
                last['stamp_s'] = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < a.warm_up:
            rclpy.spin_once(node, timeout_sec=0.1)
        r0 = rss_kb(fusion.pid)
        e0, f0 = int(last.get('epochs', 0)), int(last.get('fixes', 0))
        s0 = last.get('stamp_s', 0.0)
        t1 = time.monotonic()
        print(f'warm-up done: RSS {r0 / 1024:.1f} MiB, epochs {e0}, fixes {f0}', flush=True)
        next_report = t1 + 60
        while time.monotonic() - t1 < a.duration:
            rclpy.spin_once(node, timeout_sec=0.1)
            if time.monotonic() >= next_report:
                next_report += 60
                r = rss_kb(fusion.pid)
                print(f'{time.monotonic() - t1:6.0f} s: RSS {r / 1024:.1f} MiB '
                      f'({100 * (r - r0) / r0:+.2f} %), epochs {last.get("epochs")}, fixes '
                      f'{last.get("fixes")}, live {len(last.get("live_stations", "").split(","))}',
                      flush=True)
        t_end = time.monotonic()
        end_deadline = t_end + 3
        while time.monotonic() < end_deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        r1 = rss_kb(fusion.pid)
        e1, f1 = int(last.get('epochs', 0)), int(last.get('fixes', 0))
        # Observation cycles between the two diagnostics the counters come from.
        cycles = (last.get('stamp_s', 0.0) - s0) * a.rate
        print(f'stations {a.stations} x {a.rate:g} Hz, {a.duration:.0f} s after a '
              f'{a.warm_up:.0f} s warm-up')
        print(f'RSS {r0 / 1024:.1f} -> {r1 / 1024:.1f} MiB: {100 * (r1 - r0) / r0:+.2f} %')
        print(f'fixes {f1 - f0} of {cycles:.0f} observation cycles: '
              f'{100 * (f1 - f0) / max(cycles, 1e-9):.2f} %; fixes / epochs '
              f'{100 * (f1 - f0) / max(1, e1 - e0):.2f} %')
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        for p in (pub, fusion):
            if p.poll() is None:
                interrupt(p, 10)


if __name__ == '__main__':
    main()
