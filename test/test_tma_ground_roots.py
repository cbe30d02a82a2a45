"""Ground-speed prior with an observer faster than the target: the two ranges of (T8), (T23).

An aircraft at 100 m/s (3 km up) tracks a vehicle at 18 m/s for 300 s, a bearing a second,
σ 0.2°. Both roots of (T8) are positive for either heading of the vehicle below; for a
straight-flying observer both tracks give the same bearings exactly, so no fix may be
``ok``; a turn of the observer separates them. Fixed seeds; tolerances derived in comments.
"""
import numpy as np
import pytest

from bearing_loc_ros.core import tma as T
from bearing_loc_ros.core.tma import roots

TIMES = np.arange(300.0)
P0 = np.array([10e3, 20e3, 0.0])
V_OBS = np.array([100.0, 0.0, 0.0])
STRAIGHT = np.array([0.0, 0.0, 3000.0]) + np.outer(TIMES, V_OBS)
SIG = np.deg2rad(0.2)
HEADINGS = ([15.0, -10.0, 0.0], [-15.0, 10.0, 0.0])   # true root the smaller / the larger
M = 200


def _turning(angle_deg, at=150.0):
    """East at 100 m/s, then a turn of ``angle_deg`` at ``at`` s, on at 100 m/s."""
    a, b = np.minimum(TIMES, at), np.maximum(TIMES - at, 0.0)
    th = np.deg2rad(angle_deg)
    return (np.array([0.0, 0.0, 3000.0]) + np.outer(a, V_OBS)
            + np.outer(b, [100.0 * np.cos(th), 100.0 * np.sin(th), 0.0]))


def _nees(r, truth):
    ok = np.nonzero(r.status == 'ok')[0]
    e = r.position[ok] - truth
    return np.array([x @ np.linalg.solve(c[:3, :3], x) for x, c in zip(e, r.covariance[ok])])


def test_the_mirror_root_has_the_stated_ground_speed():
    # (T23): k x is on |v + v_o| = v_c whenever x is, k = (|v_o|² − v_c²)/|v|².
    rng = np.random.default_rng(3)
    vt = rng.normal(0.0, 20.0, (50, 3))
    vo = rng.normal(0.0, 100.0, (50, 3))
    v = vt - vo
    vc = np.linalg.norm(vt, axis=-1)
    k = roots.mirror_scale(v, vo, vc)
    two = np.isfinite(k)
    assert two.any() and not two.all()
    np.testing.assert_allclose(np.linalg.norm(k[two, None] * v[two] + vo[two], axis=-1),
                               vc[two], rtol=1e-9)
    assert np.all(k[two] > 0)
    # No second positive root when the observer is slower than the target.
    assert np.all(~two[np.linalg.norm(vo, axis=-1) < vc])
    assert roots.ROOT_THRESHOLD == pytest.approx(10.83, abs=0.01)


@pytest.mark.parametrize('vt', HEADINGS)
@pytest.mark.parametrize('method', ['tma_ctls6', 'tma_mle', 'tma_ple'])
def test_a_straight_fast_observer_gives_no_ok_fix_from_two_ground_ranges(method, vt):
    vt = np.array(vt)
    vc = float(np.linalg.norm(vt))
    bs, t = T.simulate_tma(TIMES, P0, vt, STRAIGHT, SIG, rng=np.random.default_rng(0), M=M)
    r = T.tma(method, bs, t, vc, speed_reference='ground')
    # Both ranges fit the bearings exactly as well: never 'ok', never a position.
    assert np.all(r.status == 'unobservable')
    assert all('two ranges fit the ground speed prior' in x for x in r.reason)
    assert np.all(np.isnan(r.position))
    bs0, t0 = T.simulate_tma(TIMES, P0, vt, STRAIGHT, SIG)
    r0 = T.tma(method, bs0, t0, vc, speed_reference='ground')
    assert r0.status[0] == 'unobservable'
    # The recursive window of the fusion node says the same.
    acc = T.TmaAccumulator(vc, speed_reference='ground')
    for k in range(len(TIMES)):
        acc.add(TIMES[k], STRAIGHT[k], bs0.azimuth[0, k], bs0.elevation[0, k], SIG, SIG)
    assert acc.estimate(method).status[0] == 'unobservable'


@pytest.mark.parametrize('vt', HEADINGS)
def test_a_turn_separates_the_two_ground_ranges_and_the_fix_is_right(vt):
    vt = np.array(vt)
    obs = _turning(90.0)
    bs, t = T.simulate_tma(TIMES, P0, vt, obs, SIG, rng=np.random.default_rng(0), M=M)
    r = T.tma_mle(bs, t, float(np.linalg.norm(vt)), speed_reference='ground')
    assert np.all(r.status == 'ok'), set(r.reason)
    truth = P0 + vt * TIMES[-1]
    nees = _nees(r, truth)
    # NEES of an efficient fix ~ χ²₃: mean 3 with standard error sqrt(6/200) = 0.17 (bound
    # 5 of them); above χ²₃(0.9999) = 21.1 with probability 1e-4 each, 0.02 expected in 200:
    # 3 or more has a Poisson probability of 1.3e-6. The wrong range is 7 km off (NEES 1e4).
    assert nees.mean() < 3.0 + 5.0 * np.sqrt(6.0 / M)
    assert np.sum(nees > 21.1) <= 2
    np.testing.assert_allclose(np.median(r.velocity, axis=0), vt, atol=1.0)
    # The same through the recursive window (start from the sums, then both ranges).
    acc = T.TmaAccumulator(float(np.linalg.norm(vt)), speed_reference='ground')
    for k in range(len(TIMES)):
        acc.add(TIMES[k], obs[k], bs.azimuth[0, k], bs.elevation[0, k], SIG, SIG)
    one = acc.estimate('tma_mle')
    assert one.status[0] == 'ok'
    np.testing.assert_allclose(one.position[0], r.position[0], atol=1e-3)


def test_an_inconsistent_ground_prior_says_so():
    # Seed001-like geometry: observer at 250 m/s, target at 349 m/s; a prior of 0.3 × the
    # target's speed has no positive range (T8) for a straight observer.
    times = np.arange(0.0, 100.0 + 1e-9, 0.2)
    obs = np.array([0.0, 250.0, 0.0]) * times[:, None]
    vt = np.array([-340.0, 80.0, -1.21])
    bs, t = T.simulate_tma(times, [100e3, 100e3, 10e3], vt, obs, np.deg2rad(0.1),
                           rng=np.random.default_rng(0), M=5)
    for method in ('tma_mle', 'tma_ctls6'):
        r = T.tma(method, bs, t, 0.3 * float(np.linalg.norm(vt)), speed_reference='ground')
        assert np.all(r.status == 'degenerate_geometry')
        assert all(x.startswith('speed prior inconsistent with the bearings') for x in r.reason)
