"""Parse time and outcome of hostile inputs: UDP datagrams and bearing messages.

Sends N fuzzed UDP datagrams (plus the single-datagram repros: a 400-digit azimuth,
t = 1e200000 and t = 1e999990, azimuth 1e300) through core.station.parse_datagram, and N
malformed bearing messages through ros_conversions.bearing_from_msg; prints the median,
99.9th percentile and worst parse time and the counts by outcome (accepted or rejection
reason). Any exception other than the documented one is counted as ``CRASH:<type>``.

    .venv/bin/python bench/bench_fuzz_inputs.py [--n 100000] [--seed 1]
"""

import argparse
from collections import Counter
import math
import random
import time

import numpy as np

REPROS = (b'{"t": 1700000000, "azimuth_deg": 1' + b'0' * 400 + b'}',
          b'{"t": 1e200000, "azimuth_deg": 1}', b'{"t": 1e999990, "azimuth_deg": 1}',
          b'{"t": 1700000000, "azimuth_deg": 1e300}')
KEYS = ('t', 'azimuth_deg', 'elevation_deg', 'sigma_deg', 'sigma_elevation_deg', 'x')
VALID = b'{"t": 1700000000.25, "azimuth_deg": 12.5, "elevation_deg": 3, "sigma_deg": 1}'


def hostile_literal(rng):
    k = rng.randrange(9)
    if k == 0:
        return str(rng.randint(1, 9)) + '0' * rng.randrange(20, 5000)
    if k == 1:
        return f'{rng.choice(["", "-"])}1e{rng.randrange(-10 ** 7, 10 ** 7)}'
    if k == 2:
        return rng.choice(['NaN', 'Infinity', '-Infinity', 'null', 'true', '"1"', '[]', '{}'])
    if k == 3:
        return '[' * rng.randrange(1, 3000)
    if k == 4:
        return '0.' + '0' * rng.randrange(0, 400) + '1'
    return repr(rng.uniform(-1.0, 1.0) * 10.0 ** rng.randrange(-5, 308)) if k == 5 \
        else repr(rng.uniform(-720, 720))


def datagram(rng):
    k = rng.randrange(4)
    if k == 0:
        return rng.randbytes(rng.randrange(0, 300))
    if k == 1:
        i = rng.randrange(len(VALID))
        return VALID[:i] + rng.randbytes(rng.randrange(1, 10)) + VALID[i + 1:]
    parts = [f'"{key}": {hostile_literal(rng)}' for key in KEYS if rng.random() < 0.7]
    return ('{' + ', '.join(parts) + '}').encode()[:rng.choice([100, 10 ** 6])]


def bench_datagrams(n, rng):
    from bearing_loc_ros.core.station import parse_datagram, ReadingError
    inputs = list(REPROS) + [datagram(rng) for _ in range(n)]
    times, outcome = np.empty(len(inputs)), Counter()
    worst = (0.0, b'')
    for i, data in enumerate(inputs):
        t0 = time.perf_counter()
        try:
            parse_datagram(data)
            outcome['accepted'] += 1
        except ReadingError as exc:
            outcome[exc.reason] += 1
        except Exception as exc:  # noqa: B902 - counted, this is what the bench looks for
            outcome[f'CRASH:{type(exc).__name__}'] += 1
        times[i] = time.perf_counter() - t0
        if times[i] > worst[0]:
            worst = (times[i], data[:60])
    repro_worst = times[:len(REPROS)].max()
    # A single slow sample may be the scheduler (2 shared cores): re-time the 50 slowest
    # inputs 5 times each and keep each one's best, the parse's own cost.
    retimed = []
    for i in np.argsort(times)[-50:]:
        best = math.inf
        for _ in range(5):
            t0 = time.perf_counter()
            try:
                parse_datagram(inputs[i])
            except ReadingError:
                pass
            best = min(best, time.perf_counter() - t0)
        retimed.append((best, inputs[i][:60]))
    return times, outcome, worst, repro_worst, max(retimed)


def bearing_messages(n, rng):
    from bearing_loc_ros import ros_conversions as rc
    from bearing_loc_ros.core.bearings import Bearing
    base = rc.bearing_to_msg(Bearing('s', 1_700_000_000_000_000_000, np.array([1., 2., 3.]),
                                     0.5, 0.2, 0.01, 0.02, 'map', np.eye(3)))
    nasty = [math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, 0.0, -1.0, 1e30, 1e-30]
    for _ in range(n):
        msg = type(base)()
        msg.header.frame_id = rng.choice(['map', 'map', '', 'odom'])
        msg.header.stamp.sec = rng.choice([1_700_000_000, 0, -1, 2 ** 31 - 1])
        msg.header.stamp.nanosec = rng.choice([0, 999_999_999, 10 ** 9, 4 * 10 ** 9])
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        src_p, src_o = base.pose.pose.position, base.pose.pose.orientation
        p.x, p.y, p.z = src_p.x, src_p.y, src_p.z
        o.x, o.y, o.z, o.w = src_o.x, src_o.y, src_o.z, src_o.w
        cov = list(base.pose.covariance)
        for _ in range(rng.randrange(0, 4)):
            target = rng.randrange(3)
            v = rng.choice(nasty) if rng.random() < 0.7 else rng.uniform(-1e3, 1e3)
            if target == 0:
                setattr(p, rng.choice('xyz'), v)
            elif target == 1:
                setattr(o, rng.choice('xyzw'), v)
            else:
                cov[rng.choice([0, 7, 14, rc.IDX_AZ_VAR, rc.IDX_EL_VAR])] = v
        msg.pose.covariance = cov
        yield msg


def bench_bearings(n, rng):
    from bearing_loc_ros import ros_conversions as rc
    msgs = list(bearing_messages(n, rng))
    times, outcome = np.empty(len(msgs)), Counter()
    for i, msg in enumerate(msgs):
        t0 = time.perf_counter()
        try:
            rc.bearing_from_msg(msg, 's', expected_frame='map').validate()
            outcome['accepted'] += 1
        except rc.ConversionError as exc:
            outcome[exc.reason] += 1
        except Exception as exc:  # noqa: B902 - counted, this is what the bench looks for
            outcome[f'CRASH:{type(exc).__name__}'] += 1
        times[i] = time.perf_counter() - t0
    return times, outcome


def report(title, times, outcome):
    us = times * 1e6
    print(f'{title}: {len(times)} inputs; parse time median {np.median(us):.1f} us, '
          f'99.9 % {np.percentile(us, 99.9):.1f} us, worst {us.max():.1f} us')
    for reason, count in sorted(outcome.items(), key=lambda kv: -kv[1]):
        print(f'  {reason:28s} {count:7d}')
    assert sum(outcome.values()) == len(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--n', type=int, default=100_000)
    ap.add_argument('--seed', type=int, default=1)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    times, outcome, worst, repro_worst, retimed = bench_datagrams(args.n, rng)
    report('UDP datagrams (parse_datagram)', times, outcome)
    print(f'  worst sample: {worst[1]!r}...; worst of the repros {repro_worst * 1e6:.1f} us')
    print(f'  slowest input re-timed (best of 5): {retimed[0] * 1e6:.1f} us, {retimed[1]!r}')
    times, outcome = bench_bearings(args.n, rng)
    report('bearing messages (bearing_from_msg + validate)', times, outcome)


if __name__ == '__main__':
    main()
