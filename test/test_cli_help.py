"""``bearing_loc --help`` and every verb's and sub-command's help: plain text, one example."""

import re

import pytest

from bearing_loc_ros.cli import main, VERBS

#: reStructuredText markup that must not reach a terminal.
MARKUP = re.compile(r'``|:(func|class|meth|mod|data|attr):|`[^`]+`_?|^\s*\.\. ', re.M)
SUB_COMMANDS = [['bag', c] for c in ('simulate', 'play', 'process', 'info')] + \
    [['plan', c] for c in ('cut-angle', 'map', 'place')]


def _help(capsys, argv):
    with pytest.raises(SystemExit) as exc:
        main(argv + ['--help'])
    out, err = capsys.readouterr()
    return exc.value.code, out, err


def _check(code, out, argv):
    assert code == 0, argv
    assert not MARKUP.search(out), (argv, MARKUP.search(out).group(0))
    lines = out.splitlines()
    k = lines.index('example:')
    assert lines[k + 1].startswith('  bearing_loc '), out
    if argv:
        assert lines[k + 1].split()[1] == argv[0], out
    assert 'seed 00' not in out


def test_top_level_help(capsys):
    code, out, _ = _help(capsys, [])
    _check(code, out, [])
    for verb, summary in VERBS.items():
        assert verb in out
    assert 'info' in VERBS['bag'] and 'info' in out


@pytest.mark.parametrize('verb', sorted(VERBS))
def test_every_verb_help(capsys, verb):
    code, out, _ = _help(capsys, [verb])
    _check(code, out, [verb])
    # a description besides the usage (evaluate had none)
    assert out.split('\n\n')[1].strip() and not out.split('\n\n')[1].startswith('options')


@pytest.mark.parametrize('argv', SUB_COMMANDS, ids=' '.join)
def test_sub_command_help(capsys, argv):
    code, out, _ = _help(capsys, argv)
    _check(code, out, argv)
    lines = out.splitlines()
    assert lines[lines.index('example:') + 1].split()[2] == argv[1]


def test_no_verb_prints_help_and_exits_2(capsys):
    assert main([]) == 2
    out, err = capsys.readouterr()
    # Bad input writes nothing on stdout: the help goes to stderr.
    assert out == '' and err.startswith('usage: bearing_loc') and not MARKUP.search(err)


@pytest.mark.parametrize('argv, prog, words', [
    (['locate', 'x.json', '--estimator', 'magic'], 'bearing_loc locate',
     "invalid choice: 'magic'"),
    (['locate', 'x.json', '--bogus'], 'bearing_loc locate', 'unrecognized arguments: --bogus'),
    (['--bogus'], 'bearing_loc', 'unrecognized arguments: --bogus'),
    (['--bogus', 'locate', 'x.json'], 'bearing_loc', 'unrecognized arguments: --bogus ('),
    (['bag', 'play', 'x', '--bogus'], 'bearing_loc bag play', 'unrecognized arguments: --bogus'),
    (['locate', 'x.json', '--indent', '-3'], 'bearing_loc locate', 'within 0..16'),
    (['evaluate', '--scenario', 'seed000', '--robust', '--paper'], 'bearing_loc evaluate',
     'not allowed with argument'),
    (['bag', 'simulate', '--scenario', 'seed000', '--out', 'x', '--storage', 'foo'],
     'bearing_loc bag simulate', "invalid choice: 'foo'"),
])
def test_usage_errors_are_one_line_naming_the_verb(capsys, argv, prog, words):
    # The tool's contract (docs/cli.md): bad input exits 2 with one line on stderr and
    # nothing on stdout; argparse alone would print its usage block first.
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    assert code == 2 and out == ''
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f'{prog}: error: ') and words in err, err
