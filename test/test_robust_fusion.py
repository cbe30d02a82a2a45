"""Fusion wiring of the robust fixes: fix/low_confidence, σ floors, bag process status.

The node test runs a FusionNode in-process (test_fusion_node.Harness) on the six-station
line of Zong & Cui 2015 with σ growing with range (σ_ref 3° at 1 km, capped at 6×, the
regime where the plain range-weighted ML runs away; then σ_ref 1°): every published ``fix``
must be consistent with its covariance (Mahalanobis error below the χ²₃ 0.9999 quantile), the fixes
in doubt appear only on ``fix/low_confidence`` and are counted in /diagnostics.
"""

import math

from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy import stats

from bearing_loc_ros.core.bearings import Bearing
from bearing_loc_ros.core.conventions import azimuth_elevation
from bearing_loc_ros.core.fusion import FusionConfig
from bearing_loc_ros.core.fusion.pipeline import make_core, replay
from bearing_loc_ros.ros_conversions import bearing_to_msg, fix_from_msg

S = 1_000_000_000
Q9999 = stats.chi2.ppf(0.9999, 3)
LINE = {f'st{i + 1}': np.array([x, 0.0, 0.0])
        for i, x in enumerate((-3000.0, -1800.0, -600.0, 600.0, 1800.0, 3000.0))}
QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)


def line_bearings(target, t_ns, sigma_ref, rng, grow=True):
    """Bearings of the six stations: true σ = σ_ref · clip(d / 1 km, 1, 6) (``grow``) or
    σ_ref, σ_ref reported."""
    out = []
    for name, p in LINE.items():
        az, el = azimuth_elevation(target - p)
        s = sigma_ref * (min(max(np.linalg.norm(target - p) / 1000.0, 1.0), 6.0) if grow
                         else 1.0)
        out.append(Bearing(station=name, stamp_ns=int(t_ns), position=p.copy(),
                           azimuth=float(az + s * rng.standard_normal()),
                           elevation=float(np.clip(el + s * rng.standard_normal(), -1.5, 1.5)),
                           sigma_azimuth=sigma_ref, sigma_elevation=sigma_ref))
    return out


@pytest.mark.ros
def test_node_publishes_no_confident_wrong_fix_and_counts_low_confidence(harness):
    h = harness(stations=list(LINE), estimator='wmle', reference_range=1000.0,
                publish_low_confidence=True, max_latency=0.5)
    low = []
    h.node.create_subscription(PoseWithCovarianceStamped, 'fix/low_confidence', low.append,
                               QOS)
    rng = np.random.default_rng(3)
    core = h.fusion.core
    truth = {}
    t = 100 * S
    for k in range(120):
        # σ_ref 3° (almost no fix passes its checks), then 1° (about a third pass): the
        # published fixes are checked against the truth
        sigma = math.radians(3.0 if k < 80 else 1.0)
        h.set_clock(t)
        target = rng.uniform([-3000.0, 1000.0, -500.0], [3000.0, 7000.0, 500.0])
        truth[t] = target
        done = core.fixes + sum(core.no_fix.values())
        for b in line_bearings(target, t, sigma, rng):
            h.send(bearing_to_msg(b), b.station)
        assert h.spin(lambda: core.fixes + sum(core.no_fix.values()) > done), k
        t += S
    n_low = core.no_fix['low_confidence']
    assert h.spin(lambda: len(h.fixes) == core.fixes and len(low) == n_low)
    assert n_low >= 60 and core.fixes >= 5
    for msg in h.fixes:
        stamp, x, P = fix_from_msg(msg)
        e = x - truth[stamp]
        assert e @ np.linalg.solve(P, e) < Q9999
    for msg in low:                          # low_confidence fixes carry their covariance
        stamp, x, P = fix_from_msg(msg)
        assert stamp in truth and np.all(np.isfinite(x)) and np.all(np.isfinite(P))

    def counted(d):
        v = {kv.key: kv.value for kv in d['fusion'].values} if 'fusion' in d else {}
        return v.get('low_confidence_fixes') == str(n_low)

    d = h.diag(counted)['fusion']
    values = {kv.key: kv.value for kv in d.values}
    assert int(values['low_confidence_fixes']) == n_low


def test_sigma_floor_parameters_reach_the_trust_and_are_checked():
    cfg = FusionConfig.from_parameters({'sigma_floor_deg': 1.0,
                                        'station_sigma_floors': ['s5:4.0']})
    core = make_core(cfg, stations=['s1', 's2'])
    trust = core.strategy.trust
    assert trust.sigma_floor == pytest.approx(math.radians(1.0))
    assert trust.floors == {'s5': pytest.approx(math.radians(4.0))}
    core.reconfigure(sigma_floor_deg=2.0, station_sigma_floors=[])
    assert trust.sigma_floor == pytest.approx(math.radians(2.0)) and trust.floors == {}
    for bad in (['s1'], ['s1:x'], ['s1:-1'], [':2'], ['s1:1', 's1:2'], ['a:b:1']):
        with pytest.raises(ValueError, match='station_sigma_floors'):
            FusionConfig.from_parameters({'station_sigma_floors': bad})
    with pytest.raises(ValueError, match='sigma_floor_deg'):
        FusionConfig(sigma_floor_deg=float('nan')).validate()
    for bad in (' ', 'my map', 'map\n'):
        with pytest.raises(ValueError, match='frame_id: must be a non-empty name'):
            FusionConfig(frame_id=bad).validate()


@pytest.mark.ros
def test_a_floor_for_a_station_not_listed_is_warned_about(ros, capfd):
    from rclpy.parameter import Parameter
    from bearing_loc_ros.fusion_node import FusionNode
    node = FusionNode(context=ros, namespace='floors', parameter_overrides=[
        Parameter('stations', value=['s1', 's2']),
        Parameter('station_sigma_floors', value=['s1:1.0', 'sl:2.0'])])
    try:
        err = capfd.readouterr().err
        assert 'station_sigma_floors names sl, not in stations' in err, err
    finally:
        node.destroy_node()


def test_sigma_floor_raises_a_too_good_claim_in_the_fix():
    # One station claims 1e-5 rad (its real error is 3 mrad like the others'). Every fix uses
    # its bearing with at least the floor (0.5 deg), also once the trust has verified it.
    rng = np.random.default_rng(5)
    target = np.array([500.0, 4000.0, 300.0])
    items = []
    for k in range(20):
        t = (k + 1) * S
        for b in line_bearings(target, t, 3e-3, rng, grow=False):
            if b.station == 'st3':
                b = Bearing(station=b.station, stamp_ns=b.stamp_ns, position=b.position,
                            azimuth=b.azimuth, elevation=b.elevation, sigma_azimuth=1e-5,
                            sigma_elevation=1e-5)
            items.append((t, b))
    items.append((23 * S, None))
    floor = math.radians(0.5)
    core = make_core(FusionConfig(trigger='timer', rate=1.0, max_latency=0.5, estimator='mle',
                                  station_sigma_floors=('st3:0.5',)), stations=list(LINE))
    eps = [e for e in replay(core, items) if e.ok]
    assert len(eps) >= 15
    for e in eps:
        used = {b.station: b for b in e.bearings}
        if 'st3' in used:
            assert used['st3'].sigma_azimuth >= floor
            assert used['st3'].sigma_elevation >= floor
        assert all(b.sigma_azimuth < floor for n, b in used.items() if n != 'st3')
        d = e.position - target
        assert d @ np.linalg.solve(e.covariance, d) < Q9999


def _liar_items(epochs=30):
    """Six stations on a line; st2 is biased by 1 deg and claims 1e-4 rad (a suspect)."""
    rng = np.random.default_rng(11)
    target = np.array([500.0, 4000.0, 300.0])
    items = []
    for k in range(epochs):
        t = (k + 1) * S
        for b in line_bearings(target, t, 3e-3, rng, grow=False):
            if b.station == 'st2':
                b = Bearing(station=b.station, stamp_ns=b.stamp_ns, position=b.position,
                            azimuth=b.azimuth + math.radians(1.0), elevation=b.elevation,
                            sigma_azimuth=1e-4, sigma_elevation=1e-4)
            items.append((t, b))
    return items


def _run(items, settle=None, immediate=False):
    core = make_core(FusionConfig(estimator='mle'), stations=list(LINE))
    trust = core.strategy.trust
    if immediate:      # the trust updated inside the epoch, as before the deferral
        trust.defer_update = trust.update
    out = []
    for now, b in items:
        eps = core.add_bearing(b, now)
        out += [(e.stamp_ns, e.reason, None if e.position is None else e.position.tolist(),
                 None if e.covariance is None else e.covariance.tolist(),
                 [(u.station, u.sigma_azimuth, u.sigma_elevation) for u in e.bearings])
                for e in eps]
        if settle == 'always' or (settle == 'odd' and len(out) % 2):
            core.settle()
    return out, {s: trust.scale(s) for s in LINE}, trust.suspects()


def test_deferred_trust_update_gives_the_same_fixes():
    """The node settles the station trust after publishing; offline replay never calls
    settle; both equal updating inside the epoch, bit for bit, also while a biased
    station is being scaled."""
    items = _liar_items()
    reference = _run(items, immediate=True)
    fixes, scales, suspects = reference
    assert len([f for f in fixes if f[1] == 'ok']) >= 25
    assert suspects == ['st2'] and scales['st2'] > 10.0
    assert any(u == ('st2', 1e-4 * scales['st2'], 1e-4 * scales['st2'])
               for u in fixes[-1][4])          # the liar is used with its scaled σ
    for settle in (None, 'always', 'odd'):
        assert _run(items, settle) == reference, settle


SQUARE = {'s1': (0.0, 0.0, 0.0), 's2': (10000.0, 0.0, 0.0), 's3': (0.0, 10000.0, 0.0),
          's4': (10000.0, 10000.0, 0.0), 's5': (5000.0, -3000.0, 0.0),
          's6': (-3000.0, 5000.0, 0.0)}
TARGET = np.array([5000.0, 4000.0, 1000.0])


def _square_run(n, estimator, bad, epochs=40, seed=0, start=0, azimuth_only=False):
    """(epochs, core) of the first ``n`` SQUARE stations observing TARGET with σ 3 mrad, s3
    replaced by ``bad(position, az, el) -> (position, az, el, σ)`` from epoch ``start`` on;
    ``azimuth_only``: no elevations, the horizontal solve at TARGET's altitude."""
    rng = np.random.default_rng(seed)
    stations = dict(list(SQUARE.items())[:n])
    options = {'target_altitude': float(TARGET[2])} if azimuth_only else {}
    core = make_core(FusionConfig(estimator=estimator, estimator_options=options),
                     stations=list(stations))
    out = []
    for k in range(epochs):
        t = 10 ** 12 + k * 200_000_000
        for name, p in stations.items():
            p = np.array(p)
            az, el = azimuth_elevation(TARGET - p)
            sigma = 3e-3
            if name == 's3' and k >= start:
                p, az, el, sigma = bad(p, az, el)
            el = float(el + 3e-3 * rng.standard_normal())
            b = Bearing(station=name, stamp_ns=t, position=np.asarray(p, dtype=float),
                        azimuth=float(az + 3e-3 * rng.standard_normal()),
                        elevation=math.nan if azimuth_only else el, sigma_azimuth=sigma,
                        sigma_elevation=math.nan if azimuth_only else sigma)
            out += core.add_bearing(b, t + 1000)
    return out, core


def _s3_neutralised(e):
    """s3 left out of the fix, or kept with the trust's σ at least 4 × the honest 3 mrad."""
    return all(b.sigma_azimuth >= 4 * 3e-3 for b in e.bearings if b.station == 's3')


def _confidently_wrong(eps):
    return [e for e in eps if e.ok and (e.position - TARGET) @ np.linalg.solve(
        e.covariance, e.position - TARGET) > Q9999]


@pytest.mark.parametrize('case', ['tiny sigma', 'far position'])
def test_a_station_that_makes_the_set_singular_is_dropped_not_every_epoch(case):
    # s3 claims 1e-9 rad with a 2 deg error after 15 honest epochs (its trust verified), or
    # a position 1000 km off from the start: the full set is
    # degenerate (the information's condition number beyond 1e12, or the closed form's
    # start). Before, every epoch was degenerate_geometry and nobody was blamed; now the
    # station the others' fix refutes is rejected, counted, and becomes a suspect.
    if case == 'tiny sigma':
        def bad(p, az, el):
            return p, az + math.radians(2.0), el, 1e-9
    else:
        def bad(p, az, el):
            return np.array([1.0e6, 0.0, 0.0]), az, el, 3e-3
    tiny = case == 'tiny sigma'
    eps, core = _square_run(6 if tiny else 4, 'mle', bad, epochs=55 if tiny else 40,
                            start=15 if tiny else 0)
    assert len(eps) >= 39 and all(e.ok for e in eps), {e.reason for e in eps}
    assert not _confidently_wrong(eps)
    attacked = [e for e in eps if e.stamp_ns >= 10 ** 12 + (15 if tiny else 0) * 200_000_000]
    assert len(attacked) >= 39 and all(_s3_neutralised(e) for e in attacked)
    assert core.strategy.trust.suspects() == ['s3']


@pytest.mark.parametrize('bias_deg', [2.0, 5.0])
@pytest.mark.parametrize('estimator', ['mle', 'ctls_am'])
def test_three_stations_with_one_biased_station_fix_without_it(estimator, bias_deg):
    # Two elevations and an azimuth more than the three unknowns: after the gate drops the
    # biased s3 the pair left still has a degree of freedom to check it, so the fixes are ok,
    # s3 is the suspect, and its bearing is used with a raised σ once its trust knows.
    def bad(p, az, el):
        return p, az + math.radians(bias_deg), el, 3e-3
    eps, core = _square_run(3, estimator, bad)
    assert len(eps) == 40 and all(e.ok for e in eps), {e.reason for e in eps}
    assert all(_s3_neutralised(e) for e in eps)
    assert core.strategy.trust.suspects() == ['s3']


@pytest.mark.parametrize('estimator', ['ls', 'tls', 'ctls_am', 'mle'])
def test_a_drop_that_leaves_no_redundancy_gives_no_fix(estimator):
    # Three azimuth-only stations in the plane, s3 5 deg off: any two azimuths intersect, so
    # once one is dropped nothing checks the other two and the drop may have removed an
    # honest station (ls and tls dropped s2 and published fixes ~700 m off as ok). Such an
    # epoch is low_confidence and no station is blamed.
    def bad(p, az, el):
        return p, az + math.radians(5.0), el, 3e-3
    eps, core = _square_run(3, estimator, bad, azimuth_only=True)
    assert len(eps) == 40 and not any(e.ok for e in eps)
    dropped = [e for e in eps if e.rejected]
    assert all(e.reason == 'low_confidence' and e.detail.startswith(
        'no redundancy left after dropping') for e in dropped)
    assert core.strategy.trust.suspects() == []
