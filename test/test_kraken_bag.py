"""``bag import`` of recorded KrakenSDR logs, then ``bag process``: the expected fixes.

Three fixed stations record two transmitters on two channels (433.92 MHz and 145.5 MHz);
each log has one line per channel per frame. The imported bag holds one bearing topic per
channel and station (``/<channel>/<station>/bearing``) plus /clock; processing each channel's
namespace localizes its transmitter within the fix covariance.
"""

import math

import numpy as np
import pytest
import yaml

from bearing_loc_ros import bagio
from bearing_loc_ros.bag_import import import_logs
from bearing_loc_ros.bag_process import fusion_params, process_bag
from bearing_loc_ros.cli import main as cli_main
from bearing_loc_ros.core import kraken
from bearing_loc_ros.core.bearings import BearingSet
from bearing_loc_ros.core.calibration import true_compass
from bearing_loc_ros.core.horizontal import locate_horizontal

STATIONS = {'north': ([0.0, 2000.0, 0.0], 10.0), 'west': ([-1500.0, -500.0, 0.0], 250.0),
            'east': ([1800.0, -300.0, 0.0], 95.0)}
TX = {'uhf': (np.array([300.0, 400.0, 0.0]), 433.92e6),
      'vhf': (np.array([-400.0, 900.0, 0.0]), 145.5e6)}
SIGMA_DEG = 1.5
T0_MS = 1_700_000_000_000
FRAMES = 40


def params():
    common = {'kraken': {'channels': ['uhf', 'vhf'],
                         'channel_bands_mhz': [430.0, 440.0, 144.0, 146.0],
                         'sigma_conf1_deg': SIGMA_DEG, 'sigma_conf0_deg': SIGMA_DEG}}
    out = {'/**': {'ros__parameters': common}}
    for s, (pos, heading) in STATIONS.items():
        out[f'/{s}/station_node'] = {'ros__parameters': {
            'position': pos, 'kraken': {'array_heading_deg': heading}}}
    return out


def write_logs(d, rng, t0_ms=T0_MS):
    logs = {}
    for s, (pos, heading) in STATIONS.items():
        lines = []
        for k in range(FRAMES):
            ms = t0_ms + 1000 * k + int(rng.integers(0, 40))   # stations not in lockstep
            for ch, (tx, freq) in TX.items():
                beta = math.degrees(true_compass(pos[:2], tx[:2])) + rng.normal(0, SIGMA_DEG)
                doa = (heading - beta) % 360.0
                lines.append(kraken.csv_line(kraken.KrakenRecord(
                    ms * 10 ** 6, s, freq, doa, (360.0 - doa) % 360.0, 0.95, -40.0)))
        lines.insert(5, 'a line the receiver garbled')
        logs[s] = d / f'{s}.csv'
        logs[s].write_text('\n'.join(lines) + '\n')
    return logs


@pytest.fixture(scope='module')
def imported(tmp_path_factory):
    d = tmp_path_factory.mktemp('kbag')
    logs = write_logs(d, np.random.default_rng(7))
    summary = import_logs(logs, d / 'bag', params(), clock_rate=10.0)
    return d, logs, summary


def test_a_log_from_a_receiver_whose_clock_was_not_set_imports(tmp_path):
    # A live station refuses TIME before 2000 (unset_clock); a log keeps its recorded times.
    logs = write_logs(tmp_path, np.random.default_rng(7), t0_ms=3_600_000)
    summary = import_logs(logs, tmp_path / 'bag', params(), clock_rate=10.0)
    assert all(n == FRAMES for n in summary['per_topic'].values())
    assert summary['rejected'] == {st: {'malformed_csv': 1} for st in STATIONS}
    with bagio.BagReader(tmp_path / 'bag') as r:
        msgs = list(r.messages(['/uhf/north/bearing']))
    stamps = [bagio.stamp_ns(bagio.deserialize(m.raw, m.msgtype)) for m in msgs]
    assert len(stamps) == FRAMES and 3_600_000 <= min(stamps) // 10 ** 6 < 3_700_000


def test_no_valid_reading_names_the_rejections(tmp_path):
    bad = {s: tmp_path / f'{s}.csv' for s in STATIONS}
    for path in bad.values():
        path.write_text('garbled\nnot, a, reading\n')
    with pytest.raises(ValueError, match=r'no valid reading in any log \(rejected: east: 2 '
                                         r'malformed_csv; north: 2 malformed_csv; west: 2 '
                                         r'malformed_csv\)'):
        import_logs(bad, tmp_path / 'bag', params())


def test_import_topics_and_counts(imported):
    d, _, s = imported
    assert sorted(s['topics']) == sorted(f'/{c}/{st}/bearing' for c in TX for st in STATIONS)
    assert all(n == FRAMES for n in s['per_topic'].values())
    assert s['rejected'] == {st: {'malformed_csv': 1} for st in STATIONS}
    with bagio.BagReader(d / 'bag') as r:
        topics = r.topics
        assert topics[bagio.CLOCK_TOPIC].msgtype == bagio.CLOCK
        msgs = list(r.messages(['/uhf/north/bearing']))
    m = bagio.deserialize(msgs[0].raw, msgs[0].msgtype)
    assert bagio.stamp_ns(m) == msgs[0].log_time_ns          # bag time = receiver TIME
    assert bagio.position_of(m).tolist() == STATIONS['north'][0]
    assert m.pose.covariance[35] == pytest.approx(math.radians(SIGMA_DEG) ** 2)


def epoch_fixes(epochs):
    """(position, covariance) of each 3-station epoch: the fusion's fix, or, where the
    fusion has no azimuth-only solve (``no_elevation``), the core's horizontal MLE of the
    epoch's aligned bearings with the transmitter altitude 0."""
    out = []
    for e in epochs:
        if e.ok:
            out.append((e.position, e.covariance))
        elif e.reason == 'no_elevation' and len(e.bearings) == 3:
            bs = BearingSet.from_arrays(np.array([b.position for b in e.bearings]),
                                        np.array([b.azimuth for b in e.bearings]),
                                        sigma_az=np.array([b.sigma_azimuth
                                                           for b in e.bearings]),
                                        validate=False)
            f = locate_horizontal('mle', bs, 0.0)
            out.append((f.position[0], f.covariance[0]))
    return out


@pytest.mark.parametrize('channel', sorted(TX))
def test_bag_process_localizes_each_channel(imported, channel, tmp_path):
    d, _, _ = imported
    p = fusion_params(None, ['min_stations=3'])
    s = process_bag(d / 'bag', tmp_path / f'fix_{channel}', p, namespace=channel)
    assert sorted(s['stations']) == sorted(STATIONS)
    assert s['bad_messages'] == 0 and s['dropped'] == {}
    fixes = epoch_fixes(s['epoch_list'])
    assert len(fixes) == FRAMES                  # one aligned 3-station epoch per frame
    tx = TX[channel][0]
    nees = [float((x[:2] - tx[:2]) @ np.linalg.solve(c[:2, :2], x[:2] - tx[:2]))
            for x, c in fixes]
    # consistent fixes: the mean of 40 chi2(2) values has mean 2 and sd 0.32; [0.9, 3.3]
    # is beyond its 99.9 % band
    assert 0.9 < np.mean(nees) < 3.3, np.mean(nees)


def test_bag_import_cli(imported, tmp_path, capsys):
    d, logs, _ = imported
    pfile = tmp_path / 'stations.yaml'
    pfile.write_text(yaml.safe_dump(params()))
    argv = ['bag', 'import', '--params', str(pfile), '--out', str(tmp_path / 'b')]
    for s, path in logs.items():
        argv += ['--station', f'{s}={path}']
    assert cli_main(argv) == 0
    out = capsys.readouterr().out
    assert '/uhf/north/bearing: 40 bearings' in out and 'malformed_csv 1' in out
    assert cli_main(argv) == 2                                # never overwrites a bag
    assert 'exists' in capsys.readouterr().err
    bad = ['bag', 'import', '--station', f'north={logs["north"]}', '--out',
           str(tmp_path / 'c')]
    assert cli_main(bad) == 2                                 # no position for north
    assert 'position' in capsys.readouterr().err
