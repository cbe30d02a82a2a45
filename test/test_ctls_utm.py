"""ctls_am in large absolute (UTM-like) coordinates: the one-problem and batch paths agree.

core/constrained_tls.py solves ``ctls_am`` in coordinates centred on the station centroid
(translation invariant in exact arithmetic). Before, with stations near (8e6, 9e6) m the
pseudo-linear residuals h_i X − h_i p_i cancelled ~1e7 m to metres, the cost carried
1e-11..1e-10 relative rounding, and the one-problem path (core/ctls_single.py) and the batch
path stopped differently: statuses ``ok`` against ``max_iterations``/``diverged`` and fixes
up to 2e-9 of the range apart for the seeds below.
"""

import numpy as np
import pytest

from bearing_loc_ros.core.bearings import BearingSet, simulate_bearings
from bearing_loc_ros.core.estimators import locate

OFFSET = np.array([8e6, 9e6, 0.0])       # UTM-like easting/northing, m


def problems(seed, N, M=5):
    """M problems of N stations (mixed 1D/2D, the first 2D) within ±10 km, σ = 1 mrad,
    targets 2..10 km from the origin at 0.5..5 km altitude."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1, 1, (M, N, 3)) * [10e3, 10e3, 500.0]
    ang = rng.uniform(-np.pi, np.pi, M)
    rad = rng.uniform(2e3, 10e3, M)
    tgt = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), rng.uniform(500, 5e3, M)])
    has_el = rng.random((M, N)) < 0.5
    has_el[:, 0] = True
    bs = simulate_bearings(tgt, pos, 1e-3, rng=rng)
    el = np.where(has_el, bs.elevation, np.nan)
    return tgt, BearingSet.from_arrays(bs.positions, bs.azimuth, el, bs.sigma_az, bs.sigma_el)


def shifted(bs, offset):
    return BearingSet.from_arrays(bs.positions + offset, bs.azimuth, bs.elevation,
                                  bs.sigma_az, bs.sigma_el)


def rms_range(x, positions):
    return np.sqrt(np.mean(np.sum((x - positions) ** 2, axis=-1)))


# (seed, N): before centring, 2 and 7 put the paths 1.2e-9 and 2.3e-9 of the range apart,
# 14 gave a status different from the unshifted problem's, 18 one different from the batch's.
@pytest.mark.parametrize('seed, N', [(2, 3), (7, 3), (14, 50), (18, 50)])
def test_ctls_am_paths_agree_in_utm_coordinates(seed, N):
    _, bs = problems(seed, N)
    utm = shifted(bs, OFFSET)
    batch = locate('ctls_am', utm, consistency=False)
    plain = locate('ctls_am', bs, consistency=False)           # the same, origin near
    for m in range(utm.M):
        one = locate('ctls_am', utm.problem(m), consistency=False)
        assert one.status[0] == batch.status[m] == plain.status[m], m
        assert one.status[0] == 'ok', m
        scale = rms_range(one.position[0], utm.positions[m])
        assert np.linalg.norm(one.position[0] - batch.position[m]) <= 1e-9 * scale, m
        assert np.linalg.norm(one.position[0] - OFFSET - plain.position[m]) <= 1e-9 * scale
        np.testing.assert_allclose(one.covariance[0], batch.covariance[m], rtol=1e-7,
                                   atol=1e-9 * np.abs(batch.covariance[m]).max())


def test_ctls_am_initial_is_shifted_with_the_centre():
    # Option ``initial`` is given in the caller's coordinates on both paths: started at the
    # true targets, the fixes are those started from X_LS.
    tgt, bs = problems(7, 3)
    utm = shifted(bs, OFFSET)
    ref = locate('ctls_am', utm, consistency=False)
    batch = locate('ctls_am', utm, consistency=False, initial=tgt + OFFSET)
    for m in range(utm.M):
        one = locate('ctls_am', utm.problem(m), consistency=False, initial=tgt[m] + OFFSET)
        scale = rms_range(ref.position[m], utm.positions[m])
        for res, i in ((one, 0), (batch, m)):
            assert res.status[i] == 'ok'
            assert np.linalg.norm(res.position[i] - ref.position[m]) <= 1e-9 * scale


def test_ctls_is_not_centred():
    # The paper's G holds the station coordinates (F_4): ``ctls`` depends on the origin and
    # is solved in the given coordinates (metres apart here), unlike ``ctls_am``.
    _, bs = problems(7, 3)
    far = locate('ctls', shifted(bs, OFFSET), consistency=False).position - OFFSET
    near = locate('ctls', bs, consistency=False).position
    assert np.all(np.linalg.norm(far - near, axis=1) > 0.1)
