"""docs/safety.md is the project's safety specification: every citation of it resolves, and
every one of its sections is cited by at least one test.

The oracle is the document itself (its numbered ``## N. Title`` headings), read here
independently of any code that cites it.
"""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / 'docs' / 'safety.md'

#: a citation: ``safety.md §8`` / ``safety.md §1–§9, §11`` / ``safety.md §14 and §15``
CITATION = re.compile(r'safety\.md((?:\s*(?:,|–|-|and)?\s*§\d+)+)')
SECTION = re.compile(r'§(\d+)')
#: the old form, which pointed at a file outside the project (``../shared/design``)
OLD = re.compile(r'SAFETY(?:\.md)?\b')


def sections() -> dict[int, str]:
    found = {}
    for line in DOC.read_text(encoding='utf-8').splitlines():
        m = re.match(r'## (\d+)\. (\S.*)$', line)
        if m:
            found[int(m.group(1))] = m.group(2)
    return found


def sources(*globs: str) -> list[Path]:
    files: list[Path] = []
    for pattern in globs:
        files.extend(sorted(ROOT.glob(pattern)))
    return [f for f in files if f.is_file()]


def cited(path: Path) -> list[tuple[int, int]]:
    """(line, section) of every citation in ``path``; a range ``§1–§9`` cites each."""
    out = []
    text = path.read_text(encoding='utf-8')
    for m in CITATION.finditer(text):
        line = text.count('\n', 0, m.start()) + 1
        numbers = [int(n) for n in SECTION.findall(m.group(1))]
        ranged = re.findall(r'§(\d+)\s*[–-]\s*§(\d+)', m.group(1))
        for lo, hi in ranged:
            numbers.extend(range(int(lo), int(hi) + 1))
        out.extend((line, n) for n in numbers)
    return out


CODE = ('brace_control/**/*.py', 'test/*.py', 'docs/*.md', 'README.md', 'bench/*.py',
        'scripts/*.py', 'launch/*.py', 'config/*.yaml', 'test/data/*.yaml')


def test_the_document_numbers_its_sections_one_to_n_without_gaps():
    numbers = sorted(sections())
    assert numbers, f'{DOC}: no "## N. Title" section'
    assert numbers == list(range(1, len(numbers) + 1)), numbers


def test_every_citation_in_the_project_resolves_to_a_section():
    known = sections()
    bad = [f'{p.relative_to(ROOT)}:{line}: §{n}'
           for p in sources(*CODE) if p != Path(__file__).resolve()
           for line, n in cited(p) if n not in known]
    assert not bad, 'citations of docs/safety.md with no such section:\n' + '\n'.join(bad)


def test_no_citation_points_outside_the_project():
    old = []
    for p in sources(*CODE):
        if p == Path(__file__).resolve():
            continue
        for i, line in enumerate(p.read_text(encoding='utf-8').splitlines(), 1):
            if OLD.search(line):
                old.append(f'{p.relative_to(ROOT)}:{i}: {line.strip()}')
    assert not old, 'cite docs/safety.md §N, not a file outside the project:\n' + '\n'.join(old)


def test_every_section_is_cited_by_at_least_one_test():
    by_tests = {n for p in sources('test/test_*.py') if p != Path(__file__).resolve()
                for _, n in cited(p)}
    missing = {n: title for n, title in sections().items() if n not in by_tests}
    assert not missing, f'sections of docs/safety.md no test cites: {missing}'


def test_the_readme_links_the_project_s_own_safety_document():
    readme = (ROOT / 'README.md').read_text(encoding='utf-8')
    assert 'docs/safety.md' in readme


def test_the_citation_reader_reads_lists_and_ranges(tmp_path):
    f = tmp_path / 'x.py'
    f.write_text('# docs/safety.md §1–§3, §11 and §14\n# safety.md §8\n', encoding='utf-8')
    assert sorted(n for _, n in cited(f)) == [1, 1, 2, 3, 3, 8, 11, 14]
