"""Fast paths of the fusion's per-epoch work give the results of their plain definitions.

``station_trust.deletion_residuals`` (one numpy pass over an epoch) against
``deletion_residual`` (one bearing at a time), and the trust scale against np.median."""
import numpy as np
import pytest

from bearing_loc_ros.core import station_trust as st
from bearing_loc_ros.core.bearings import Bearing


def epoch(rng, n, on_axis=False):
    """n bearings (every third azimuth-only) to a random emitter, and a random fix."""
    x = rng.normal(0.0, 3000.0, 3)
    x[2] = abs(x[2]) + 100.0
    items = []
    for i in range(n):
        p = rng.normal(0.0, 5000.0, 3)
        if on_axis and i == 0:
            p = x - [0.0, 0.0, 10.0]             # straight below: untestable
        d = x - p
        az = float(np.arctan2(d[1], d[0]) + rng.normal(0.0, 0.01))
        el = (float(np.arctan2(d[2], np.hypot(d[0], d[1])) + rng.normal(0.0, 0.01))
              if i % 3 else float('nan'))
        sigma = float(rng.uniform(1e-3, 2e-2))
        items.append((Bearing(f's{i}', 0, p, az, el, sigma, sigma if el == el else np.nan),
                      bool(rng.random() < 0.8)))
    A = rng.normal(size=(3, 3))
    P = A @ A.T * 100.0 + np.eye(3)
    claims = {f's{i}': (0.005, 0.006) for i in range(0, n, 2)}
    return items, claims, x, P


@pytest.mark.parametrize('seed', range(40))
def test_batched_deletion_residuals_equal_the_plain_path(seed):
    rng = np.random.default_rng(seed)
    items, claims, x, P = epoch(rng, int(rng.integers(2, 40)), on_axis=seed % 5 == 0)
    F = np.linalg.inv(P)
    fast = st.deletion_residuals(items, claims, x, P, F)
    plain = [st.deletion_residual(b, inside, claims, x, P, F) for b, inside in items]
    assert len(fast) == len(plain)
    if seed % 5 == 0:
        assert fast[0] is None                   # the station below the fix
    for a, b in zip(fast, plain):
        assert (a is None) == (b is None)
        if a is not None:
            assert a[1] == b[1]
            np.testing.assert_allclose([a[0], a[2]], [b[0], b[2]], rtol=1e-9, atol=0.0)


def test_singular_stack_falls_back_to_the_plain_path():
    # A fix from exactly two 1D bearings: removing either leaves a singular information.
    rng = np.random.default_rng(5)
    items, claims, x, P = epoch(rng, 2)
    items = [(Bearing(b.station, 0, b.position, b.azimuth), True) for b, _ in items]
    F = np.linalg.inv(P)
    fast = st.deletion_residuals(items, {}, x, P, F)
    plain = [st.deletion_residual(b, True, {}, x, P, F) for b, _ in items]
    assert [r is None for r in fast] == [r is None for r in plain]


def test_trust_update_and_scale_match_the_definition():
    rng = np.random.default_rng(3)
    trust = st.StationTrust(window=6)
    for _ in range(9):
        items, claims, x, P = epoch(rng, 12)
        inside = [b for b, i in items if i]
        outside = [b for b, i in items if not i]
        F = np.linalg.inv(P)
        got = trust.update(inside, claims, x, P, outside)
        for b in inside + outside:
            row = st.deletion_residual(b, b in inside, claims, x, P, F)
            if row is None:
                assert b.station not in got
            else:
                np.testing.assert_allclose(got[b.station], row[2], rtol=1e-9)
    scaled = 0
    for station, h in trust._hist.items():
        # Scaled only when the window's Σ d² exceeds its χ² quantile (module doc).
        dof = sum(k for _, k, _, _ in h)
        gate = sum(d for _, _, d, _ in h) > st._chi2.ppf(trust.probability, dof)
        expect = np.sqrt(max(1.0, float(np.median([e / k for e, k, _, _ in h]))))
        assert trust.scale(station) == (expect if gate else 1.0)
        scaled += gate and expect > 1.0
    assert scaled > 0                    # the gated branch is exercised


def test_station_leaving_two_angles_is_untestable_on_both_paths():
    # Two 2D stations: without one, the other's two angles leave the fix undetermined, and
    # P_(-k) is the inverse of a numerically singular matrix (cond ~1e16) whose smallest
    # eigenvalue has a random sign. Both paths must call such a station untestable.
    x = np.array([2500.0, 3000.0, 800.0])
    items = []
    for p in ([0.0, 0.0, 0.0], [6000.0, -1000.0, 20.0]):
        d = x - p
        items.append((Bearing(f's{len(items)}', 0, np.array(p), float(np.arctan2(d[1], d[0])),
                              float(np.arctan2(d[2], np.hypot(d[0], d[1]))), 3e-3, 3e-3),
                      True))
    F = np.zeros((3, 3))                 # the fix's information: both stations' angles
    for b, _ in items:
        J, _, R = st._angles(b, x)
        F += J.T @ np.diag(1.0 / R) @ J
    P = np.linalg.inv(F)
    assert st.deletion_residuals(items, {}, x, P, F) == [None, None]
    assert [st.deletion_residual(b, i, {}, x, P, F) for b, i in items] == [None, None]
    assert st.StationTrust().update([b for b, _ in items], {}, x, P) == {}
