"""Record every input of the fusion pipeline (core.fusion.FusionCore), live or offline.

``python test/fusion_recorder.py <file> --ros-args ...`` runs the fusion node with each
``FusionCore.add_bearing(bearing, now)`` and ``FusionCore.tick(now)`` call appended to
``<file>`` (pickles) before it runs; :func:`recording` does the same in-process (for
``bag process``). :func:`replay_calls` feeds such a recording to a fresh core: the pipeline
never reads a clock, so it returns the epochs of the recorded run, bit for bit.
"""
from contextlib import contextmanager
import pickle
import sys

from bearing_loc_ros.core.fusion import pipeline


@contextmanager
def recording(path):
    """Append ('bearing', now_ns, Bearing) / ('tick', now_ns, None) to ``path`` for every
    FusionCore input made inside the block."""
    add, tick = pipeline.FusionCore.add_bearing, pipeline.FusionCore.tick
    with open(path, 'ab') as out:
        def add_bearing(self, bearing, now_ns):
            pickle.dump(('bearing', None if now_ns is None else int(now_ns), bearing), out)
            out.flush()
            return add(self, bearing, now_ns)

        def tick_at(self, now_ns):
            pickle.dump(('tick', int(now_ns), None), out)
            out.flush()
            return tick(self, now_ns)

        pipeline.FusionCore.add_bearing, pipeline.FusionCore.tick = add_bearing, tick_at
        try:
            yield
        finally:
            pipeline.FusionCore.add_bearing, pipeline.FusionCore.tick = add, tick


def load_calls(path):
    """The recorded calls of ``path``: list of (kind, now_ns, Bearing or None)."""
    calls = []
    with open(path, 'rb') as f:
        while True:
            try:
                calls.append(pickle.load(f))
            except EOFError:
                return calls


def replay_calls(core, calls):
    """Make the recorded ``calls`` on ``core``; return the epochs, in order."""
    epochs = []
    for kind, now, bearing in calls:
        epochs += core.add_bearing(bearing, now) if kind == 'bearing' else core.tick(now)
    return epochs


def arrivals(calls):
    """The bearings of ``calls`` as (now_ns, station, stamp_ns), in handling order."""
    return [(now, b.station, b.stamp_ns) for kind, now, b in calls if kind == 'bearing']


if __name__ == '__main__':
    from bearing_loc_ros.fusion_node import main
    path = sys.argv.pop(1)
    with recording(path):
        main()
