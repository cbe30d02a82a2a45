"""``bearing_loc`` against hostile input and output streams and paths: a closed stdin, a
stdout that is closed, full or a pipe nobody reads, output files that cannot be written
(a directory, a path ending in '/', /proc), the input file given as an output, CSV tables
with a byte order mark or in another encoding. Each is one line on stderr and exit 2 (a
closed pipe: a quiet exit), never a traceback, and nothing on stdout."""
import errno
import io
import json
import os
import subprocess
import sys
import types

import numpy as np
import pytest
import yaml

from bearing_loc_ros.cli import main
from bearing_loc_ros.core import kraken

EXE = os.path.join(os.path.dirname(sys.executable), 'bearing_loc')
needs_exe = pytest.mark.skipif(not os.path.exists(EXE),
                               reason='bearing_loc console script not installed')
needs_proc = pytest.mark.skipif(not os.path.isdir('/proc'),
                                reason='needs /proc (a directory no file can be created in)')
ORIGIN = ['--origin', '48', '11', '500']
REQUEST = {'estimator': 'mle', 'bearings': [
    {'station': 's1', 'position': [30000, -10000, 100], 'azimuth': 2.0344,
     'elevation': 0.1729, 'sigma_azimuth': 0.0015, 'sigma_elevation': 0.0015},
    {'station': 's2', 'position': [30000, 20000, 200], 'azimuth': 3.1416, 'elevation': None,
     'sigma_azimuth': 0.0015},
    {'station': 's3', 'position': [-30000, 5000, 150], 'azimuth': 0.3230, 'elevation': 0.1236,
     'sigma_azimuth': 0.0015, 'sigma_elevation': 0.0015}]}
TMA_REQUEST = {'speed': 100.0, 'sigma_azimuth': 0.002, 'sigma_elevation': 0.002,
               'observations': [{'t': float(t), 'observer': [100.0 * t, 0.0, 0.0],
                                 'azimuth': 1.0 + 0.01 * t, 'elevation': 0.1}
                                for t in range(6)]}
TABLE = ('problem,x,y,z,azimuth,sigma_azimuth,station\n'
         '0,30000,-10000,100,2.0344,0.0015,s1\n'
         '0,30000,20000,200,3.1416,0.0015,s2\n'
         '0,-30000,5000,150,0.3218,0.0015,s3\n')
STATIONS_2D = ['--stations', '20,0,0;-20,0,0', '--sigma-deg', '0.1', '--altitude', '3000']


def run(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def one_error(code, out, err, prog, message):
    """Exit 2, nothing on stdout, and exactly the line ``<prog>: error: <message>...``."""
    assert code == 2 and out == '', (code, out, err)
    assert len(err.splitlines()) == 1 and 'Traceback' not in err, err
    assert err.startswith(f'{prog}: error: {message}'), err


@pytest.fixture
def request_file(tmp_path):
    path = tmp_path / 'req.json'
    path.write_text(json.dumps(REQUEST))
    return str(path)


# ------------------------------------------------------------------------------ closed stdin

@pytest.mark.parametrize('argv', [['locate'], ['locate', '--format', 'csv'],
                                  ['locate', '--format', 'npz', '-'], ['tma']])
def test_closed_stdin_is_one_line(capsys, monkeypatch, argv):
    # Python sets sys.stdin to None when file descriptor 0 is closed (`bearing_loc locate <&-`)
    monkeypatch.setattr('sys.stdin', None)
    one_error(*run(capsys, argv), f'bearing_loc {argv[0]}',
              'input: cannot read stdin: it is closed')


@needs_exe
def test_closed_stdin_in_a_real_process():
    p = subprocess.run(['sh', '-c', '"$0" locate <&-', EXE], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 2 and p.stdout == ''
    assert p.stderr.splitlines() == ['bearing_loc locate: error: input: cannot read stdin: it '
                                     'is closed']


# ---------------------------------------------------------------------------------- stdout

class FullStdout:
    """A stdout on a full disk: every write fails with ENOSPC."""

    def write(self, text):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def flush(self):
        pass


@pytest.mark.parametrize('verb', ['locate', 'tma'])
def test_stdout_that_cannot_be_written_is_one_line(capsys, monkeypatch, tmp_path, verb):
    path = tmp_path / 'in.json'
    path.write_text(json.dumps(REQUEST if verb == 'locate' else TMA_REQUEST))
    for stdout, why in ((FullStdout(), os.strerror(errno.ENOSPC)), (None, 'it is closed')):
        monkeypatch.setattr('sys.stdout', stdout)
        code = main([verb, str(path)])
        err = capsys.readouterr().err
        assert code == 2 and err.splitlines() == [
            f'bearing_loc {verb}: error: stdout: cannot write ({why})'], err


@needs_exe
@pytest.mark.skipif(not os.path.exists('/dev/full'), reason='needs /dev/full')
@pytest.mark.parametrize('argv', [['locate', '{req}'], ['tma', '{tma}'],
                                  ['plan', 'cut-angle', '--k1', '1']])
def test_dev_full_in_a_real_process(tmp_path, argv):
    # Also the interpreter's own flush at exit must not fail again ("Exception ignored").
    (tmp_path / 'req.json').write_text(json.dumps(REQUEST))
    (tmp_path / 'tma.json').write_text(json.dumps(TMA_REQUEST))
    argv = [a.format(req=tmp_path / 'req.json', tma=tmp_path / 'tma.json') for a in argv]
    with open('/dev/full', 'w') as full:
        p = subprocess.run([EXE, *argv], stdout=full, stderr=subprocess.PIPE, text=True,
                           timeout=60)
    verb = ' '.join(argv[:1])
    assert p.returncode == 2, p.stderr
    assert p.stderr.splitlines() == [f'bearing_loc {verb}: error: stdout: cannot write (No '
                                     'space left on device)']


@needs_exe
def test_a_reader_that_stops_ends_the_command_quietly(tmp_path):
    # ~400 kB of results: far more than a pipe holds, so writes after the reader left fail
    path = tmp_path / 'batch.json'
    path.write_text(json.dumps({'problems': [{'bearings': REQUEST['bearings']}] * 400}))
    p = subprocess.Popen([EXE, 'locate', str(path)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    assert p.stdout.read(10) == b'{"results"'
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) == 0 and err == ''


# ------------------------------------------------------------------------------ output files

@pytest.mark.parametrize('flag', ['--geojson', '--kml', '--geo-csv'])
def test_locate_export_to_a_directory(capsys, tmp_path, request_file, flag):
    (tmp_path / 'd').mkdir()
    for path in (str(tmp_path / 'd'), str(tmp_path / 'd') + '/', str(tmp_path / 'new') + '/'):
        one_error(*run(capsys, ['locate', request_file, flag, path, *ORIGIN]),
                  'bearing_loc locate', f'{flag}: cannot write {path!r} (is a directory')
    assert os.listdir(tmp_path / 'd') == []


@needs_proc
@pytest.mark.parametrize('flag', ['--geojson', '--kml', '--geo-csv'])
def test_locate_export_that_cannot_be_created(capsys, request_file, flag):
    one_error(*run(capsys, ['locate', request_file, flag, '/proc/x.out', *ORIGIN]),
              'bearing_loc locate', f"{flag}: cannot write '/proc/x.out' (No such file")


def test_locate_export_over_the_input_or_another_output(capsys, tmp_path, request_file):
    before = open(request_file).read()
    alias = os.path.join(os.path.dirname(request_file), '.', 'req.json')
    for path in (request_file, alias):
        one_error(*run(capsys, ['locate', request_file, '--geo-csv', path, *ORIGIN]),
                  'bearing_loc locate', f'--geo-csv: {path!r} is the input file')
    assert open(request_file).read() == before
    out = str(tmp_path / 'out.txt')
    one_error(*run(capsys, ['locate', request_file, '--geojson', out, '--kml', out, *ORIGIN]),
              'bearing_loc locate', f"--kml: {out!r} is also the file of --geojson")
    code, out, err = run(capsys, ['locate', request_file, '--geojson', str(tmp_path / 'a.json'),
                                  '--kml', str(tmp_path / 'a.kml'), *ORIGIN])
    assert code == 0 and err == '' and json.loads(out)['status'] == 'ok'


@needs_proc
def test_plan_map_kml_overlay_that_cannot_be_written(capsys):
    one_error(*run(capsys, ['plan', 'map', *STATIONS_2D, '--resolution', '6000', '--kml',
                            '/proc/x.kml', *ORIGIN]),
              'bearing_loc plan', "--kml: cannot write '/proc/x_accuracy.png' (No such file")


@pytest.mark.parametrize('argv, flag', [
    (['map'], '--png'), (['place', '--area-km', '5'], '--png-before'),
    (['place', '--area-km', '5'], '--png-after')])
def test_plan_image_to_a_directory(capsys, tmp_path, argv, flag):
    # an existing directory gave DIR.png beside it, a trailing '/' a hidden DIR/.png
    (tmp_path / 'd').mkdir()
    for path in (str(tmp_path / 'd'), str(tmp_path / 'd') + '/', str(tmp_path / 'e') + '/'):
        one_error(*run(capsys, ['plan', *argv, *STATIONS_2D, flag, path]),
                  'bearing_loc plan', f'{flag}: {path!r} is a directory')
    assert sorted(os.listdir(tmp_path)) == ['d'] and os.listdir(tmp_path / 'd') == []


@pytest.mark.parametrize('sub', [['map'], ['place', '--area-km', '5']])
def test_plan_colour_scale_limits(capsys, sub):
    one_error(*run(capsys, ['plan', *sub, *STATIONS_2D, '--vmin', '100', '--vmax', '10']),
              'bearing_loc plan', '--vmin: must be below --vmax')
    one_error(*run(capsys, ['plan', *sub, *STATIONS_2D, '--vmax', '-3']),
              'bearing_loc plan', '--vmax: must be a finite number > 0')


@pytest.fixture(scope='module')
def calibration_files(tmp_path_factory):
    from test_calibration import params, simulate, STATIONS, TX
    d = tmp_path_factory.mktemp('calibrate')
    rng = np.random.default_rng(1)
    argv = ['calibrate', '--transmitter', *map(str, TX)]
    for s in STATIONS:
        (d / f'{s}.csv').write_text(''.join(kraken.csv_line(r) + '\n'
                                            for r in simulate(rng, 200, s)))
        argv += ['--station', f'{s}={d / s}.csv']
    (d / 'stations.yaml').write_text(yaml.safe_dump(
        {f'/{s}/station_node': {'ros__parameters': p} for s, p in params().items()}))
    return d, argv + ['--params', str(d / 'stations.yaml')]


def test_calibrate_prints_nothing_when_out_cannot_be_written(capsys, calibration_files):
    d, argv = calibration_files
    bad = [str(d), str(d) + '/']
    if os.path.isdir('/proc'):
        bad.append('/proc/o.yaml')      # fails only when written, after the fit
    for out in bad:
        one_error(*run(capsys, argv + ['--out', out]), 'bearing_loc calibrate',
                  f'out: cannot write {out}')
    code, out, err = run(capsys, argv + ['--out', str(d / 'ok.yaml')])
    assert code == 0 and out.splitlines()[-1] == f'wrote {d / "ok.yaml"}'
    assert 'heading bias' in out and (d / 'ok.yaml').exists()


# ----------------------------------------------------------------------------- CSV encodings

@pytest.mark.parametrize('source', ['file', 'stdin'])
def test_csv_with_a_byte_order_mark(capsys, monkeypatch, tmp_path, source):
    data = b'\xef\xbb\xbf' + TABLE.encode()      # as Excel writes "CSV UTF-8"
    code, out, err = run_table(capsys, monkeypatch, tmp_path, source, data)
    assert code == 0, err
    ref = run_table(capsys, monkeypatch, tmp_path, source, TABLE.encode())
    assert out == ref[1] and json.loads(out)['results'][0]['status'] == 'ok'


@pytest.mark.parametrize('source', ['file', 'stdin'])
def test_csv_not_utf8_is_refused_from_file_and_stdin(capsys, monkeypatch, tmp_path, source):
    data = TABLE.replace('s1', 's\xe91').encode('latin-1')
    one_error(*run_table(capsys, monkeypatch, tmp_path, source, data), 'bearing_loc locate',
              'input: the CSV is not UTF-8 text')


def run_table(capsys, monkeypatch, tmp_path, source, data):
    argv = ['locate', '--target-altitude', '3000']
    if source == 'file':
        (tmp_path / 't.csv').write_bytes(data)
        return run(capsys, argv + [str(tmp_path / 't.csv')])
    monkeypatch.setattr('sys.stdin', types.SimpleNamespace(buffer=io.BytesIO(data)))
    return run(capsys, argv + ['--format', 'csv', '-'])


def test_npz_errors_print_plain_numbers(capsys, tmp_path):
    np.savez(tmp_path / 'p.npz', problem=np.array([0.0, 0.5]), x=np.zeros(2), y=np.zeros(2),
             z=np.zeros(2), azimuth=np.zeros(2), sigma_azimuth=np.ones(2))
    one_error(*run(capsys, ['locate', str(tmp_path / 'p.npz')]), 'bearing_loc locate',
              'row 1: problem: must be an integer id, got 0.5')


def test_locate_geo_csv_alone_builds_no_map_features(capsys, tmp_path, request_file,
                                                     monkeypatch):
    # The rays and ellipses of the map formats took 47 s for 10,000 fixes that the CSV
    # does not hold.
    from bearing_loc_ros.core import gis

    def refuse(*args, **kwargs):
        raise AssertionError('feature_collection called for --geo-csv alone')
    monkeypatch.setattr(gis, 'feature_collection', refuse)
    out = tmp_path / 'fixes.csv'
    code, _, err = run(capsys, ['locate', request_file, '--geo-csv', str(out), *ORIGIN])
    assert code == 0, err
    assert out.read_text().startswith('stamp_ns,time,x_m')


def test_plan_map_kml_image_must_not_overwrite_the_heat_map(capsys, tmp_path):
    # --kml m.kml writes its map image to m_accuracy.png: with --png m_accuracy.png the heat
    # map was silently replaced by the overlay.
    png, kml = tmp_path / 'm_accuracy.png', tmp_path / 'm.kml'
    one_error(*run(capsys, ['plan', 'map', '--stations', '0,0,0;20,0,0', '--altitude', '500',
                            '--sigma-deg', '0.1', '--png', str(png), '--kml', str(kml),
                            *ORIGIN]),
              'bearing_loc plan', f"--kml: its map image {str(png)!r} is also the file of --png")
    assert not png.exists() and not kml.exists()
