"""The user manual (README.md and docs/*.md) stays short, linked and free of working notes.

Checks: the README fits (<= 260 lines) and gives the two set-up commands; every relative
link and image in README.md and docs/*.md points to an existing file and, for a Markdown
target, to an existing heading anchor (GitHub's slug rules) or explicit ``<a id>``; the papers
are cited by author, never as "seed 00N"; no absolute machine path; every docs page starts
with a title and has a table of contents.
"""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'
DOCS = sorted((ROOT / 'docs').glob('*.md'))
PAGES = [README] + DOCS

LINK = re.compile(r'!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)\)')
HEADING = re.compile(r'^(#{1,6}) +(.*?) *#*$')
EXPLICIT_ANCHOR = re.compile(r'<a id="([^"]+)"')


def _rel(path):
    return str(path.relative_to(ROOT))


def _outside_code(text):
    """Lines of ``text`` outside fenced code blocks, with inline code spans kept."""
    out, fence = [], False
    for line in text.split('\n'):
        if line.lstrip().startswith('```'):
            fence = not fence
            out.append('')
            continue
        out.append('' if fence else line)
    return out


def github_slug(heading):
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r'`', '', heading.strip()).lower()
    text = re.sub(r'[^\w\- ]', '', text)
    return text.replace(' ', '-')


def anchors(path):
    """Every anchor a link into ``path`` may use (duplicates numbered as GitHub does)."""
    seen, result = {}, set()
    lines = _outside_code(path.read_text(encoding='utf-8'))
    for line in lines:
        m = HEADING.match(line)
        if m:
            slug = github_slug(m.group(2))
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            result.add(slug if n == 0 else f'{slug}-{n}')
        result.update(EXPLICIT_ANCHOR.findall(line))
    return result


def links(path):
    """(line number, target) of every Markdown link and image outside code blocks."""
    for no, line in enumerate(_outside_code(path.read_text(encoding='utf-8')), 1):
        line = re.sub(r'`[^`]*`', '', line)
        for m in LINK.finditer(line):
            yield no, m.group(1)


def test_github_slug_follows_githubs_rules():
    assert github_slug('`wmle`: range-weighted maximum likelihood') == \
        'wmle-range-weighted-maximum-likelihood'
    assert github_slug('Optimal cut angle of a 2D + 1D pair') == \
        'optimal-cut-angle-of-a-2d--1d-pair'
    assert github_slug('The Cramér-Rao lower bound') == 'the-cramér-rao-lower-bound'


def test_readme_fits_and_gives_the_two_setup_commands():
    text = README.read_text(encoding='utf-8')
    assert len(text.splitlines()) <= 260
    assert 'make demo' in text
    assert 'make test' in text


def test_docs_pages_exist():
    names = {p.name for p in DOCS}
    for page in ('nodes.md', 'cli.md', 'estimators.md', 'tma.md', 'planning.md', 'bags.md',
                 'conventions.md', 'design.md', 'references.md', 'benchmarks.md'):
        assert page in names, page
    assert not (ROOT / 'docs' / 'HELPERS.md').exists()


@pytest.mark.parametrize('page', PAGES, ids=_rel)
def test_every_relative_link_points_to_an_existing_file_and_anchor(page):
    broken = []
    for no, target in links(page):
        if re.match(r'^[a-z][a-z0-9+.-]*:', target) or target.startswith('//'):
            continue  # http(s), mailto: not checked offline
        file_part, _, anchor = target.partition('#')
        dest = page if not file_part else (page.parent / file_part).resolve()
        if not dest.exists():
            broken.append(f'{_rel(page)}:{no}: {target}: no such file')
            continue
        if anchor and dest.suffix == '.md' and anchor not in anchors(dest):
            broken.append(f'{_rel(page)}:{no}: {target}: no such anchor')
    assert not broken, '\n'.join(broken)


@pytest.mark.parametrize('page', PAGES, ids=_rel)
def test_papers_are_cited_by_author_not_by_seed_number(page):
    text = page.read_text(encoding='utf-8')
    hits = [m.group(0) for m in re.finditer(r'(?i)seed[ -]00\d', text)]
    assert not hits, f'{_rel(page)}: cite the paper by author and year: {hits}'


@pytest.mark.parametrize('page', PAGES, ids=_rel)
def test_no_absolute_machine_paths(page):
    text = page.read_text(encoding='utf-8')
    hits = re.findall(r'(?<![\w.])/(?:work|tmp|home)/\S*', text)
    assert not hits, f'{_rel(page)}: absolute machine path(s): {hits}'


@pytest.mark.parametrize('page', DOCS, ids=_rel)
def test_each_docs_page_has_a_title_and_a_table_of_contents(page):
    lines = page.read_text(encoding='utf-8').splitlines()
    assert lines and lines[0].startswith('# '), f'{_rel(page)}: first line is not a title'
    head = '\n'.join(lines[:80])
    assert '<!-- TOC -->' in head and '<!-- /TOC -->' in head, \
        f'{_rel(page)}: no table of contents near the top'
    toc = head[head.index('<!-- TOC -->'):head.index('<!-- /TOC -->')]
    assert re.search(r'^\s*- \[.+\]\(#', toc, re.M), f'{_rel(page)}: empty table of contents'
