"""Malformed bearings over DDS: a running fusion node keeps fixing and counts every message.

    .venv/bin/python bench/fuzz_dds.py [--n 100000] [--rate 2000] [--seed 1]

Starts a fusion node (``bearing_loc_ros.fusion_node``, default QoS and trigger, estimator
ls) in namespace /soak with stations s1..s4 and x1: s1..s4 are honest stations at 10 Hz
(the publisher of ``soak_fusion.py``); x1 is one process publishing ``--n`` malformed
bearings (``bench_fuzz_inputs.bearing_messages``: NaN, infinite, huge, negative or zero
variances and coordinates, bad quaternions, wrong frames, stamps of 1970, 2023 or 2038,
nanoseconds of 1e9 and 4e9; half of them re-stamped with the current time so they reach the
core's checks; only those the conversion or the core's checks reject, unless
``--keep-valid``: the rest are well-formed bearings from a lying station, the robust gate's
business, not a parser's) at ``--rate`` messages per second, best effort, keep-last 10,
then a burst of ``--burst`` messages as fast as it can (to overflow the node's keep-last
queue). All on loopback with their own ROS_DOMAIN_ID.

Prints: whether the node is still alive; the fixes while x1 sent (fixed fraction of the
observation cycles between the first and the last fix, largest gap between consecutive fix
stamps and between fix arrivals, with where the largest arrival gaps were; fixes whose
Mahalanobis error to the target is above the chi2_3 0.9999 quantile); x1's
/diagnostics counters (received, accepted, bad.*, dropped.*, lost.*) and how they account
for the messages sent (received + lost.sequence_gap = sent, except a lost tail, which no
receiver can see); the node's WARN lines (throttled, so far fewer than the messages).
"""
import argparse
from collections import Counter
import os
import re
import random
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def malformed(rng, keep_valid):
    """(message, restamp) pairs: bench_fuzz_inputs' hostile bearing messages, half of them
    to be stamped with the time they are sent; without ``keep_valid`` only those the
    conversion or the core's checks reject."""
    sys.path.insert(0, HERE)
    from bench_fuzz_inputs import bearing_messages
    from bearing_loc_ros import ros_conversions as rc
    while True:
        for msg in bearing_messages(1000, rng):
            restamp = rng.random() < 0.5
            if restamp:
                stamp(msg)
            if not keep_valid:
                try:
                    rc.bearing_from_msg(msg, 'x1', expected_frame='map').validate()
                    continue
                except ValueError:
                    pass
            yield msg, restamp


def stamp(msg):
    now = time.time_ns()
    msg.header.stamp.sec, msg.header.stamp.nanosec = now // 10 ** 9, now % 10 ** 9


def run_fuzzer(n, rate, burst, seed, keep_valid):
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from bearing_loc_ros.ros_common import keep_last_qos

    rclpy.init()
    node = rclpy.create_node('fuzz_x1', namespace='/soak')
    pub = node.create_publisher(PoseWithCovarianceStamped, 'x1/bearing',
                                keep_last_qos(10, 'best_effort'))
    rng = random.Random(seed)
    gen = malformed(rng, keep_valid)
    msgs = [next(gen) for _ in range(n + burst)]
    time.sleep(3.0)                      # matched by the node before the first message
    print('start', flush=True)
    t0 = time.monotonic()
    for i, (msg, restamp) in enumerate(msgs):
        if i < n:
            delay = t0 + i / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        if restamp:
            stamp(msg)
        pub.publish(msg)
    print(f'sent {len(msgs)} in {time.monotonic() - t0:.1f} s', flush=True)
    time.sleep(3.0)
    node.destroy_node()
    rclpy.try_shutdown()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--n', type=int, default=100_000, help='paced malformed messages')
    ap.add_argument('--rate', type=float, default=2000.0, help='messages per second')
    ap.add_argument('--burst', type=int, default=5000, help='unpaced messages at the end')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--warm-up', type=float, default=10.0)
    ap.add_argument('--keep-valid', action='store_true',
                    help='also send the generated messages that pass every check')
    ap.add_argument('--role', default='main', help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.role == 'fuzzer':
        return run_fuzzer(a.n, a.rate, a.burst, a.seed, a.keep_valid)
    repo = os.path.dirname(HERE)
    sys.path.insert(0, HERE)
    from soak_fusion import bench_env, start_publisher, TARGET
    env = bench_env(200, 30)
    fd, log_path = tempfile.mkstemp(prefix='fuzz_dds_', suffix='.log')
    log = os.fdopen(fd, 'w+')
    fusion = subprocess.Popen(
        [sys.executable, '-m', 'bearing_loc_ros.fusion_node', '--ros-args', '-r', '__ns:=/soak',
         '-p', 'stations:=[s1,s2,s3,s4,x1]', '-p', 'estimator:=ls',
         '-p', 'accuracy_map.enabled:=false', '-p', 'diagnostics_period:=0.5'],
        cwd=repo, env=env, stdout=log, stderr=subprocess.STDOUT)
    total = a.warm_up + a.n / a.rate + 60
    honest = start_publisher(env, 4, 10, total)
    import numpy as np
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from scipy.stats import chi2

    from bearing_loc_ros.processes import interrupt
    rclpy.init()
    node = rclpy.create_node('fuzz_probe')
    diag, fixes, diag_times, d2 = {}, [], [], []

    def on_diag(msg):
        diag_times.append(time.monotonic())
        for s in msg.status:
            diag[s.name.rpartition(': ')[2]] = {kv.key: kv.value for kv in s.values}

    def on_fix(msg):
        fixes.append((time.monotonic(), msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9))
        p, c = msg.pose.pose.position, np.reshape(msg.pose.covariance, (6, 6))[:3, :3]
        e = np.array([p.x, p.y, p.z]) - TARGET
        try:
            d2.append(float(e @ np.linalg.solve(c, e)))
        except np.linalg.LinAlgError:
            d2.append(np.inf)
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)
    node.create_subscription(PoseWithCovarianceStamped, '/soak/fix', on_fix, 100)

    def spin(seconds, until=None):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.02)
            if until is not None and until():
                return True
        return until is None

    fuzzer = None
    try:
        spin(a.warm_up)
        print(f'warm-up: fixes {diag.get("fusion", {}).get("fixes")}', flush=True)
        fuzzer = subprocess.Popen([sys.executable, __file__, '--role', 'fuzzer', '--n',
                                   str(a.n), '--rate', str(a.rate), '--burst', str(a.burst),
                                   '--seed', str(a.seed)] + ['--keep-valid'] * a.keep_valid,
                                  cwd=repo, env=env,
                                  stdout=subprocess.PIPE, text=True)
        fuzzer.stdout.readline()
        t0, k0 = time.monotonic(), len(fixes)
        spin(a.n / a.rate + 120, lambda: fuzzer.poll() is not None)
        t1 = time.monotonic()
        sent_line = fuzzer.stdout.read().strip()
        spin(3.0)
        alive = fusion.poll() is None
        during = [f for f in fixes[k0:] if f[0] <= t1]
        stamps = sorted({s for _, s in during})
        arrivals = [t for t, _ in during]
        cycles = round((stamps[-1] - stamps[0]) * 10) + 1 if stamps else 0
        gaps = sorted(((b - c, c - stamps[0]) for b, c in zip(stamps[1:], stamps)),
                      reverse=True)
        agaps = sorted(((b - c, c - t0) for b, c in zip(arrivals[1:], arrivals)),
                       reverse=True)
        gap, agap = (gaps or [(float('nan'), 0)])[0][0], (agaps or [(float('nan'), 0)])[0][0]
        print(f'fuzzer: {sent_line} (paced {a.n} at {a.rate:g}/s, then a burst of {a.burst})')
        print(f'fusion node alive: {alive}')
        print(f'fixes while x1 sent: {len(stamps)} of {cycles:.0f} observation cycles '
              f'({100 * len(stamps) / cycles:.2f} %); largest gap between fix stamps {gap:.3f} '
              f's, between fix arrivals {agap:.3f} s (epoch period 0.100 s)')
        bound = chi2.ppf(0.9999, 3)
        wrong = [x for x in d2[k0:] if x > bound]
        print(f'  fixes confidently wrong (Mahalanobis error² to the target above the chi2_3 '
              f'0.9999 quantile {bound:.1f}): {len(wrong)} of {len(d2) - k0}; largest '
              f'{max(d2[k0:], default=float("nan")):.1f}')
        print('  largest arrival gaps (s, at s after the start): '
              + ', '.join(f'{g:.3f} at {w:.1f}' for g, w in agaps[:3]))
        dt = [t for t in diag_times if t0 <= t <= t1]
        print(f'node responsive: largest gap between its /diagnostics (period 0.5 s) '
              f'{max((b - c for b, c in zip(dt[1:], dt)), default=float("nan")):.3f} s')
        x1 = diag.get('station x1', {})
        keys = sorted(k for k in x1 if k.split('.')[0] in
                      ('received', 'accepted', 'bad', 'dropped', 'lost', 'used', 'state'))
        print('x1 /diagnostics: ' + ', '.join(f'{k} {x1[k]}' for k in keys))
        sent = a.n + a.burst
        rec = int(x1.get('received', 0))
        seq_gaps = int(x1.get('lost.sequence_gap', 0))
        counted = int(x1.get('accepted', 0)) + sum(
            int(v) for k, v in x1.items() if k.startswith(('bad.', 'dropped.')))
        print(f'sent {sent}; received {rec} + lost.sequence_gap {seq_gaps} = '
              f'{rec + seq_gaps} (missing, a lost tail: {sent - rec - seq_gaps}); received '
              f'accounted by reason (accepted + bad.* + dropped.*): {counted} of {rec}')
        over = diag.get('fusion', {})
        print('overall: ' + ', '.join(
            f'{k} {v}' for k, v in sorted(over.items())
            if k in ('bad_messages', 'warnings_suppressed', 'epochs', 'fixes')
            or k.startswith(('dropped.', 'no_fix.', 'lost.')) and v != '0'))
        for s in ('s1', 's2', 's3', 's4'):
            st = diag.get(f'station {s}', {})
            print(f'  {s}: ' + ', '.join(f'{k} {v}' for k, v in sorted(st.items())
                                         if k in ('received', 'accepted', 'used', 'outliers')
                                         or k.startswith(('dropped.', 'lost.')) and v != '0'))
        log.flush()
        log.seek(0)
        lines = log.read().splitlines()
        warns = [x for x in lines if '[WARN]' in x or '[ERROR]' in x]
        print(f'node log: {len(warns)} WARN/ERROR lines, {len(lines)} lines; '
              f'tracebacks: {sum("Traceback" in x for x in lines)}')
        kinds = Counter(re.sub(r'[-+]?\d[\d.e+-]*', '#', w.partition(']: ')[2])[:90]
                        for w in warns)
        for text, count in kinds.most_common(4):
            print(f'  {count:5d} x {text}')
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        for p in (fuzzer, honest, fusion):
            if p is not None and p.poll() is None:
                interrupt(p, 10)
        log.close()
        os.unlink(log_path)


if __name__ == '__main__':
    main()
