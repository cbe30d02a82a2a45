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


def _gate_problem(rng, n, wrap=False, on_axis=False, sigma_el_nan=False):
    """A one-problem BearingSet (every third station azimuth-only), its σ and a fix."""
    from bearing_loc_ros.core.fusion.gating import _trusted_set
    x = rng.normal(0.0, 3000.0, 3)
    x[2] = abs(x[2]) + 100.0
    fix = x + rng.normal(0.0, 20.0, 3)
    bearings = []
    for i in range(n):
        p = rng.normal(0.0, 5000.0, 3)
        if on_axis and i == 1:
            p = fix - [0.0, 0.0, 50.0]           # the fix straight above a station
        if wrap and i == 0:
            p = x + [1000.0, rng.normal(0.0, 1e-3), 0.0]    # azimuth near ±π
        d = x - p
        az = float(np.arctan2(d[1], d[0]) + rng.normal(0.0, 0.05))
        az = float(np.arctan2(np.sin(az), np.cos(az)))
        el = (float(np.arctan2(d[2], np.hypot(d[0], d[1])) + rng.normal(0.0, 0.05))
              if i % 3 else float('nan'))
        s = float(rng.uniform(1e-3, 3e-2))
        bearings.append(Bearing(f's{i}', 0, p, az, el, s, s if el == el else np.nan))
    bs = _trusted_set(bearings)
    saz = bs.sigma_az * rng.uniform(1.0, 2.0, bs.sigma_az.shape)
    sel = bs.sigma_el.copy()
    if sigma_el_nan:
        sel[0, 1] = np.nan                       # np.nan_to_num's 1.0 on both paths
    return bs, fix, saz, sel


@pytest.mark.parametrize('seed', range(60))
def test_float_gate_equals_the_numpy_gate_bit_for_bit(seed):
    from bearing_loc_ros.core.fusion import gating
    from bearing_loc_ros.core.bearings import BearingSet
    rng = np.random.default_rng(seed)
    bs, x, saz, sel = _gate_problem(rng, int(rng.integers(2, 30)), wrap=seed % 3 == 0,
                                    on_axis=seed % 4 == 0, sigma_el_nan=seed % 5 == 0)
    gate = 0.999 if seed % 7 else 1.0
    fast = gating._gate_one(bs, x, saz, sel, gate)
    plain = gating._gate(BearingSet(bs.positions, bs.azimuth, bs.elevation, saz, sel,
                                    bs.stations), x, np.zeros((bs.N, 3, 3)), gate)
    assert fast is not None
    d2, dof, worst, top = fast
    assert np.array_equal(np.array(d2), plain[0], equal_nan=True)
    assert dof == plain[1].tolist()
    assert (worst, top) == (plain[2], plain[3])
    assert (seed % 4 == 0) == bool(np.isnan(d2).any())
    assert float(np.nansum(d2)) == float(np.nansum(plain[0]))


def test_float_gate_ties_and_zero_variance():
    from bearing_loc_ros.core.fusion import gating
    rng = np.random.default_rng(1)
    bs, x, saz, sel = _gate_problem(rng, 6)
    # Two stations with the same ratio: the first, as np.argmax.
    bs.positions[0, 4], bs.azimuth[0, 4], bs.elevation[0, 4] = (bs.positions[0, 1],
                                                                bs.azimuth[0, 1],
                                                                bs.elevation[0, 1])
    saz[0, 4], sel[0, 4] = saz[0, 1] * 1e-3, sel[0, 1] * 1e-3
    saz[0, 1], sel[0, 1] = saz[0, 4], sel[0, 4]
    worst = gating._gate_one(bs, x, saz, sel, 0.999)[2]
    assert worst == 1
    saz[0, 2] = 0.0                              # Python would raise: the numpy path
    assert gating._gate_one(bs, x, saz, sel, 0.999) is None


def _covariances(rng):
    """Covariances around the PSD boundary: well-conditioned, nearly singular, indefinite,
    asymmetric, tiny and huge scales, non-finite."""
    out = []
    for _ in range(300):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        lam = rng.uniform(0.1, 10.0, 3) * 10.0 ** rng.uniform(-8, 8)
        k = rng.integers(0, 5)
        if k == 1:
            lam[0] = lam[2] * rng.choice([1e-8, 1e-9, 1.1e-9, 9e-10, 1e-10, 1e-16, 0.0])
        elif k == 2:
            lam[0] = -lam[2] * rng.choice([1e-6, 9e-10, 1.1e-9, 1e-12])
        elif k == 3:
            lam = -lam
        c = (q * lam) @ q.T
        if rng.random() < 0.3:
            c = c + rng.normal(0.0, 1e-12, (3, 3)) * abs(c).max()
        out.append(c)
    out += [np.zeros((3, 3)), np.diag([1.0, 1.0, np.nan]), np.diag([1.0, np.inf, 1.0]),
            np.diag([1e-200, 1e-200, 1e-200]), np.diag([1e200, 1.0, 1.0]),
            np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])]
    return out


def test_covariance_ok_equals_the_eigenvalue_rule():
    from bearing_loc_ros.core.fusion import gating
    rng = np.random.default_rng(7)
    fast_taken = 0
    for c in _covariances(rng):
        with np.errstate(all='ignore'):
            plain = bool(np.all(np.isfinite(c))) and (lambda lam: bool(
                lam[-1] > 0.0 and lam[0] >= -1e-9 * lam[-1]))(
                np.linalg.eigvalsh(0.5 * (c + c.T)))
        assert gating.covariance_ok(c) == plain, c
        if np.all(np.isfinite(c)) and gating.cholesky_positive(c.tolist()):
            assert plain
            fast_taken += 1
    assert fast_taken > 100


@pytest.mark.parametrize('seed', range(12))
def test_solve_epoch_with_and_without_the_float_gate(seed, monkeypatch):
    """Epochs with gross outliers (the gate drops stations): the float gate and the numpy
    gate give the same epochs bit for bit."""
    from bearing_loc_ros.core.fusion import gating
    rng = np.random.default_rng(100 + seed)
    bs, x, _, _ = _gate_problem(rng, int(rng.integers(4, 15)), wrap=seed % 2 == 0)
    bearings = [Bearing(s, 0, bs.positions[0, i], float(bs.azimuth[0, i]),
                        float(bs.elevation[0, i]), float(bs.sigma_az[0, i]),
                        float(bs.sigma_el[0, i])) for i, s in enumerate(bs.stations)]
    for i in rng.choice(len(bearings), size=min(2, len(bearings) - 3), replace=False):
        b = bearings[i]
        bearings[i] = Bearing(b.station, 0, b.position, float(b.azimuth + 0.3), b.elevation,
                              b.sigma_azimuth, b.sigma_elevation)

    def run():
        return [gating.solve_epoch(bearings, est, {}, 2, 0.999, validated=True)
                for est in ('mle', 'ls', 'wmle')]
    fast = run()
    monkeypatch.setattr(gating, '_gate_one', lambda *a: None)
    plain = run()
    for f, p in zip(fast, plain):
        assert (f.reason, f.detail, f.chi2, f.dof) == (p.reason, p.detail, p.chi2, p.dof)
        assert f.residuals == p.residuals
        assert [b.station for b in f.rejected] == [b.station for b in p.rejected]
        for a, b in ((f.position, p.position), (f.covariance, p.covariance)):
            assert (a is None and b is None) or np.array_equal(a, b, equal_nan=True)


def test_nansum_of_a_list_is_numpys():
    from bearing_loc_ros.core.fusion.gating import _nansum
    rng = np.random.default_rng(5)
    for n in range(1, 300, 7):
        v = (rng.standard_normal(n) * 10.0 ** rng.uniform(-5, 5, n)).tolist()
        for i in rng.choice(n, size=n // 4, replace=False):
            v[i] = float('nan')
        assert _nansum(v) == float(np.nansum(np.array(v)))
    assert _nansum([float('nan')] * 3) == 0.0
    assert np.signbit(_nansum([-0.0, -0.0])) == np.signbit(np.nansum([-0.0, -0.0]))
