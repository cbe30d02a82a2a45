"""bearing_loc_ros.memory: the heap trim after dropped subscriptions is safe and counted."""

import ctypes
import gc
import sys

import pytest

from bearing_loc_ros import memory


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


class Owner:
    """A stand-in for the fusion node's subscription set (weak-referenceable)."""


class Log:
    def __init__(self):
        self.lines = []

    def debug(self, text):
        self.lines.append(text)


def trimmer(trim, interval=10.0):
    clock = Clock()
    calls = []

    def fake(pad):
        calls.append(pad)
        return trim(pad)
    return memory.HeapTrimmer(trim=fake, min_interval=interval, clock=clock), clock, calls


def test_trims_only_when_the_count_falls_then_once_more_after_the_interval():
    h, clock, calls = trimmer(lambda pad: 1)
    a, log = Owner(), Log()
    for n in (3, 10, 200, 200):          # growing or flat: nothing to give back
        assert not h.update(a, n, log)
    assert calls == []
    assert h.update(a, 3, log)           # 200 -> 3
    assert calls == [0] and h.trims == 1
    assert 'subscriptions 200 -> 3' in log.lines[-1]
    clock.t += 5.0
    assert not h.update(a, 3, log)       # the follow-up waits for the interval
    clock.t += 5.0
    assert h.update(a, 3, log)           # the follow-up trim
    clock.t += 60.0
    assert not h.update(a, 3, log)       # and no more while nothing falls
    assert h.trims == 2 and h.failures == 0 and h.deferred == 0


def test_a_fall_inside_the_interval_is_deferred_not_lost():
    h, clock, calls = trimmer(lambda pad: 1)
    a = Owner()
    h.update(a, 100)
    assert h.update(a, 50)
    clock.t += 11.0
    h.update(a, 50)                      # the follow-up
    clock.t += 1.0
    h.update(a, 80)
    assert not h.update(a, 4)            # fell, but trimmed 1 s ago
    assert h.deferred == 1 and h.trims == 2
    clock.t += 10.0
    assert h.update(a, 4)                # served once the interval has passed
    assert h.trims == 3


def test_a_failing_trim_is_counted_never_raised():
    def boom(pad):
        raise OSError('no heap for you')
    h, clock, calls = trimmer(boom)
    a, log = Owner(), Log()
    h.update(a, 5)
    assert not h.update(a, 1, log)
    assert h.failures == 1 and h.trims == 0
    assert 'malloc_trim failed' in log.lines[-1]


def test_no_trim_function_is_a_no_op():
    h = memory.HeapTrimmer(trim=None, min_interval=0.0)
    h.trim = None                        # as on a C library without malloc_trim
    a = Owner()
    h.update(a, 10)
    assert not h.update(a, 0)
    assert not h.available and h.trims == h.failures == 0


def test_one_trim_serves_every_owner_and_owners_are_weak():
    h, clock, calls = trimmer(lambda pad: 1)
    a, b = Owner(), Owner()
    h.update(a, 20)
    h.update(b, 30)
    assert h.update(a, 2)
    clock.t += 10.0
    h.update(a, 2)                       # follow-up
    clock.t += 10.0
    assert not h.update(b, 30)           # b's count did not fall since the trim
    assert len(h._high) == 2
    del b
    gc.collect()
    assert len(h._high) == 1             # a destroyed owner leaves nothing behind


def test_non_glibc_platforms_get_no_trim(monkeypatch):
    monkeypatch.setattr(sys, 'platform', 'darwin')
    assert memory.glibc_malloc_trim() is None

    def no_library(*args, **kwargs):
        raise OSError('not found')
    monkeypatch.setattr(sys, 'platform', 'linux')
    monkeypatch.setattr(ctypes, 'CDLL', no_library)
    assert memory.glibc_malloc_trim() is None
    assert not memory.HeapTrimmer().available


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='glibc only')
def test_the_real_trim_runs_on_glibc():
    trim = memory.glibc_malloc_trim()
    if trim is None:
        pytest.skip('not glibc')
    assert trim(0) in (0, 1)             # 1: memory was released, 0: none was
    h = memory.HeapTrimmer(min_interval=0.0)
    a, log = Owner(), Log()
    h.update(a, 2)
    assert h.update(a, 1, log) and h.trims == 1
    assert 'RSS' in log.lines[-1]


def test_the_fusion_discovery_trims_once_discovered_publishers_left(harness, monkeypatch):
    """The fusion node's discovery scan reports its subscriptions: publishers that appear
    and leave again make it trim the heap (a counting stand-in for malloc_trim). Without
    the discovery probe, so that the node subscribes to them itself."""
    import subprocess
    from bearing_loc_ros import fusion_wiring
    from ros_helpers import GHOST_PUBLISHERS, node_env
    calls = []
    monkeypatch.setattr(fusion_wiring, 'HEAP', memory.HeapTrimmer(
        trim=lambda pad: calls.append(pad) or 1, min_interval=0.0))
    h = harness(stations=('s1', 's2', 's3'), discover=True, discovery_period=0.1,
                discovery_probe=False)
    assert h.spin(lambda: h.fusion._subs.keys() == {'s1', 's2', 's3'})
    ghosts = subprocess.Popen([sys.executable, '-c', GHOST_PUBLISHERS, f'/{h.ns}', '20'],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                              env=node_env())
    try:
        assert ghosts.stdout.readline().strip() == 'ready'
        assert h.spin(lambda: len(h.fusion._subs) == 23, timeout=20.0)
        assert calls == []                   # subscriptions only grew
    finally:
        ghosts.stdin.close()
        ghosts.wait(timeout=20)
    assert h.spin(lambda: len(h.fusion._subs) == 3, timeout=20.0)
    assert h.spin(lambda: len(calls) >= 1, timeout=5.0)
    assert calls[0] == 0 and fusion_wiring.HEAP.failures == 0
