"""Micro-benchmark of the per-message conversions (prints µs per call; no assertions).

Times, best of 5 ``timeit`` repeats on one typical 2D bearing (and a 1D one):

* ``ros_conversions.bearing_from_msg`` on a message that went through CDR (what the fusion
  node's subscription callback receives) and ``bearing_to_msg`` (simulator, station node);
* their parts: ``Bearing.validate`` (scalar fast path) against the full vectorised field
  check it falls back to, and the scalar angle twins of ``core.conventions`` against the
  vectorised functions on one value.

``--old FILE`` also times a previous version of ros_conversions.py for comparison, loaded from
a file outside the package, for example::

    git show e4d0465~1:bearing_loc_ros/ros_conversions.py > ros_conversions_old.py
    .venv/bin/python bench/bench_conversions.py --old ros_conversions_old.py

(the old ``bearing_to_msg`` then runs with today's ``Bearing.validate``, so its figure is the
old conversion without the old 40 µs validation; the "full check" row shows that part).
"""

import argparse
import importlib.util
import os
import sys
import timeit

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from bearing_loc_ros import ros_conversions as rc  # noqa: E402
from bearing_loc_ros.core import bearings as core_bearings  # noqa: E402
from bearing_loc_ros.core import conventions as cv  # noqa: E402
from bearing_loc_ros.core.bearings import Bearing  # noqa: E402


def per_call_us(fn, repeats=5):
    """Best of ``repeats`` timeit runs (each about 0.2 s), µs per call."""
    timer = timeit.Timer(fn)
    number, _ = timer.autorange()
    return min(timer.repeat(repeats, number)) / number * 1e6


def load_old(path):
    """Import a ros_conversions.py file as bearing_loc_ros.<name> (relative imports work)."""
    spec = importlib.util.spec_from_file_location('bearing_loc_ros._bench_old_conversions',
                                                  path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def full_check(b):
    core_bearings._check_bearing_fields(
        np.asarray(b.position, dtype=float)[None, None, :],
        np.array([[b.azimuth]], dtype=float), np.array([[b.elevation]], dtype=float),
        np.array([[b.sigma_azimuth]], dtype=float), np.array([[b.sigma_elevation]], dtype=float))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--old', help='a previous ros_conversions.py to time as well')
    args = ap.parse_args()
    old = load_old(args.old) if args.old else None
    b2 = Bearing('station_1', 1_700_000_000_123_456_789, np.array([1e4, -2e3, 50.0]), 0.7,
                 0.1, 2e-3, 3e-3, 'map', np.diag([0.25, 0.25, 1.0]))
    b1 = Bearing('station_2', 1_700_000_000_123_456_789, np.array([-3e3, 5e3, 0.0]), -2.1,
                 sigma_azimuth=2e-3)
    wire = {}
    for name, b in (('2D', b2), ('1D', b1)):
        m = rc.bearing_to_msg(b)
        wire[name] = deserialize_message(serialize_message(m), type(m))
    q = cv.quaternion_from_azel(0.7, 0.1)
    qt = tuple(float(v) for v in q)
    rows = []
    for name in ('2D', '1D'):
        m, b = wire[name], (b2 if name == '2D' else b1)
        rows.append((f'bearing_from_msg ({name}, after CDR)',
                     per_call_us(lambda: rc.bearing_from_msg(m, 's', 'map')),
                     old and per_call_us(lambda: old.bearing_from_msg(m, 's', 'map'))))
        rows.append((f'bearing_to_msg ({name})', per_call_us(lambda: rc.bearing_to_msg(b)),
                     old and per_call_us(lambda: old.bearing_to_msg(b))))
    rows += [
        ('Bearing.validate (scalar fast path; right: full vectorised check)',
         per_call_us(b2.validate), per_call_us(lambda: full_check(b2))),
        ('azel_from_quaternion_scalar (right: vectorised)',
         per_call_us(lambda: cv.azel_from_quaternion_scalar(*qt)),
         per_call_us(lambda: cv.azel_from_quaternion(q))),
        ('quaternion_from_azel_scalar (right: vectorised)',
         per_call_us(lambda: cv.quaternion_from_azel_scalar(0.7, 0.1)),
         per_call_us(lambda: cv.quaternion_from_azel(0.7, 0.1))),
        ('wrap_angle_scalar (right: vectorised)', per_call_us(lambda: cv.wrap_angle_scalar(-3.2)),
         per_call_us(lambda: cv.wrap_angle(-3.2))),
    ]
    print(f'per-call cost, best of 5 (numpy {np.__version__}, Python '
          f'{sys.version.split()[0]}, {os.cpu_count()} CPUs)'
          + (f'; old = {args.old}' if old else ''))
    print('| call | now (µs) | old / vectorised (µs) |')
    print('|---|---:|---:|')
    for label, now, ref in rows:
        ref_text = f'{ref:.1f}' if ref else '–'
        print(f'| {label} | {now:.2f} | {ref_text} |')


if __name__ == '__main__':
    main()
