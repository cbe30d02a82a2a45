"""The source papers are cited by author and year everywhere, never by an internal number.

docs/references.md gives the citations: Wang, Zhang & Wu (2006), Lin et al., Zong & Cui (2015)
and Wang, Su, Bai & Zhong (2009). The shipped scenario files keep their names (``seed000.yaml``,
``--scenario seed001``): a scenario name is written without a space or hyphen, so the pattern
below (a word "seed", one space or hyphen, then 000-004) only matches prose that names a paper
by number. Every tracked text file is checked: code, tests, benches, scenarios, launch files,
the manual and the changelog.
"""
import os
import re
import subprocess

from ros_helpers import REPO

#: "seed", a space or hyphen, and a paper number: prose naming a paper by its number.
NUMBERED_PAPER = re.compile(r'(?i)\bseed[ -]00[0-4]\b')
#: Directories never part of the product when the tree is walked without git.
SKIP_DIRS = {'.git', '.venv', 'build', 'install', 'log', '__pycache__', 'node_modules'}


def _tracked_files():
    """Paths (relative to the repository) of the tracked files, or of every file without git."""
    try:
        proc = subprocess.run(['git', 'ls-files', '-z'], cwd=REPO, capture_output=True,
                              check=True)
        names = [n for n in proc.stdout.decode('utf-8').split('\0') if n]
        if names:
            return names
    except (OSError, subprocess.CalledProcessError):
        pass
    names = []
    for root, dirs, files in os.walk(REPO):
        dirs[:] = [d for d in dirs if d not in SKIP_DIRS and not d.startswith('.')]
        names += [os.path.relpath(os.path.join(root, f), REPO) for f in files]
    return names


def _text(path):
    """The file's text, or None for a binary (NUL byte or not UTF-8) or missing file."""
    try:
        with open(os.path.join(REPO, path), 'rb') as f:
            data = f.read()
    except OSError:
        return None
    if b'\0' in data:
        return None
    try:
        return data.decode('utf-8')
    except UnicodeDecodeError:
        return None


def test_pattern_tells_paper_numbers_from_scenario_names():
    # Joined at run time, so that this file does not itself hold the forbidden form.
    for before, sep, after in (('as in seed', ' ', '003 eq. (9)'), ('Seed', ' ', '000 section 4'),
                               ('the seed', '-', '001 scenario'), ('(SEED', ' ', '004, fig. 1)')):
        prose = before + sep + after
        assert NUMBERED_PAPER.search(prose), prose
    for name in ('config/scenarios/seed000.yaml', '--scenario seed001', 'seed000_azimuth_only',
                 'bench/wmle_seed003.py', 'seed000_sec4', 'random seed ' + '0004', 'seed 0',
                 'the seed 005 run'):
        assert not NUMBERED_PAPER.search(name), name


def test_no_tracked_file_cites_a_paper_by_number():
    files = _tracked_files()
    assert any(f.replace(os.sep, '/') == 'docs/references.md' for f in files), files[:20]
    hits = []
    for path in files:
        text = _text(path)
        if text is None:
            continue
        for lineno, line in enumerate(text.split('\n'), 1):
            for m in NUMBERED_PAPER.finditer(line):
                hits.append(f'{path}:{lineno}: {m.group(0)!r} in {line.strip()[:80]!r}')
    assert not hits, ('cite the paper by author and year (docs/references.md), not by number:\n'
                      + '\n'.join(hits))
