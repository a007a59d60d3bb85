"""Every number the results prose quotes has a source in a committed file it cites.

The README's results paragraphs and docs/results/README.md went stale while the reports stayed exact
(issue 47: "25 new" runs that were 30, clips of "100-257 s" that are 131.5-256.9 s). So each number
there is looked up in the files the prose cites, and a number none of them holds fails this test:

- **Cited sources** are the files a block links to (`[report](dance1_full/report.md)`) or names as a
  repository path in backticks (`sweeps/peer_samplers.yaml`, `docs/bench/2026-11-27_h100_race_*.json`:
  a glob; a folder stands for its text files), resolved against the document's folder or the
  repository root, plus an invisible `<!-- sources: PATH ... -->`. Generated files and records count
  (report.md, race tables, JSON, YAML, CSV); hand-written prose (PROSE) never does, so a figure cannot
  be sourced from another paragraph that went stale too. In docs/results/README.md a block may also
  use what the earlier blocks of its `##` section cite (a study's section cites its report once); in
  the README each checked block cites its own.
- **A number matches** a source's number when it is that number rounded as the prose rounds it:
  0.057 matches 0.0566, 1100 matches 1100.0, 2.95e7 matches 29491200, 26.8% matches 0.268 or 26.8
  (and so does the 1.5 of "1.5-1.9%"), 530k matches 530,123; signs are not compared (a "difference of
  -0.009" is a "lower by 0.00881").
- **Not looked up:** code spans (commands and settings, which other tests run), link targets, dates,
  commit hashes, issue numbers, approximate figures marked `~` or "about" (a session's monitor, not a
  file), and a block right after `<!-- numbers unchecked: REASON -->` (a record whose run folders are
  gone, a table computed from parquet tables): the reason is required, and the list stays short.
"""

from __future__ import annotations

import functools
import glob
import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.conftest import REPO

PROSE = ("README.md", "docs/benchmarks.md", "docs/architecture.md")
"""Hand-written documents (and every README.md): never a source of a number."""
TEXT_SUFFIXES = (".md", ".json", ".yaml", ".yml", ".csv", ".txt", ".sh")
"""Files of a cited folder whose numbers are read."""
MAX_UNCHECKED = 12
"""How many `numbers unchecked` markers the documents may hold: records of lost runs and tables
computed from parquet tables, not prose that went unchecked."""

_NUMBER = re.compile(
    r"(?:(?<=[\s(\[/:;,=x×≥≤<>*])|^)(?P<approx>~\s?|about\s+|approximately\s+)?[-+−]?"
    r"(?P<int>\d{1,3}(?:,\d{3})+|\d+)(?P<frac>\.\d+)?(?P<exp>e[-+]?\d+)?(?P<k>k\b)?(?P<pct>%|(?=[-–]\d+(?:\.\d+)?%))?", re.M)
_SOURCE_NUMBER = re.compile(r"\d+(?:\.\d+)?(?:e[-+]?\d+)?")
_SKIPPED = (
    (re.compile(r"`[^`\n]*`"), "code"),
    (re.compile(r"\]\([^)\n]*\)"), "]"),
    (re.compile(r"<!--.*?-->", re.S), " "),
    (re.compile(r"\b\d{4}-\d{2}-\d{2}(?:/\d{2})?\b"), "date"),
    (re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b"), "commit"),
    (re.compile(r"\b[Ii]ssues? \d+(?:(?:, | and )\d+)*"), "issue"),
)


@dataclass
class Block:
    """A paragraph, list or table of a document, with where it sits and what it cites."""

    text: str
    line: int
    cites: list[Path] = field(default_factory=list)
    unchecked: str | None = None
    """The reason given in a `<!-- numbers unchecked: ... -->` right before it (None: checked)."""


_ITEM = re.compile(r"^\s*(?:[-*]|\d+\.) ", re.M)
_MARKER = re.compile(r"<!--\s*(section )?numbers unchecked:?(.*?)-->", re.S)


def _pieces(chunk: str) -> list[tuple[int, str]]:
    """(line offset, text) of a chunk's list items (each with its continuation lines), or the whole
    chunk (a paragraph, a table)."""
    starts = [m.start() for m in _ITEM.finditer(chunk)]
    if not starts or chunk.lstrip().startswith("|"):
        return [(0, chunk)]
    bounds = ([0] if starts[0] > 0 and chunk[: starts[0]].strip() else []) + starts + [len(chunk)]
    return [(chunk[:a].count("\n"), chunk[a:b]) for a, b in zip(bounds, bounds[1:])]


def blocks(text: str, doc: Path) -> list[list[Block]]:
    """The document's `##` sections, each a list of blocks: paragraphs, list items, tables. Headings
    and fenced code are not blocks; a `numbers unchecked` marker opts out the block it is in (or, alone
    in a paragraph, the next one), a `section numbers unchecked` one every block to the next `##`."""
    text = re.sub(r"```.*?```", lambda m: "\n" * m.group().count("\n"), text, flags=re.S)
    sections: list[list[Block]] = [[]]
    line, pending, section_reason = 1, None, None
    for chunk in re.split(r"(\n\s*\n)", text):
        if re.fullmatch(r"\n\s*\n", chunk):
            line += chunk.count("\n")
            continue
        if chunk.lstrip().startswith("#"):
            if chunk.lstrip().startswith("## "):
                sections.append([])
                section_reason = None
            heading_lines = len(chunk.split("\n", 1)[0]) + 1
            line += chunk[:heading_lines].count("\n")
            chunk = chunk[heading_lines:]
        for offset, piece in _pieces(chunk):
            marker = _MARKER.search(piece)
            reason = marker.group(2).strip() if marker else None
            if marker and marker.group(1):
                section_reason = reason
                reason = None
            rest = _MARKER.sub(" ", piece)
            if not rest.strip():
                pending = reason if reason is not None else pending
                continue
            unchecked = next((r for r in (reason, pending, section_reason) if r is not None), None)
            sections[-1].append(Block(piece, line + offset, citations(piece, doc), unchecked))
            pending = None
        line += chunk.count("\n")
    return sections


def citations(text: str, doc: Path) -> list[Path]:
    """Committed files the text cites (links, backticked paths, `<!-- sources: ... -->`), prose left out."""
    names = re.findall(r"\]\(([^)#\s]+)", text)
    names += re.findall(r"`([\w.*-]+(?:/[\w.*=,-]*)+/?|[\w.*-]+\.(?:md|json|ya?ml|csv|txt|sh))`", text)
    names += [n for group in re.findall(r"<!--\s*sources:(.*?)-->", text, re.S) for n in group.split()]
    found = []
    for name in names:
        for base in (doc.parent, REPO):
            paths = [Path(p) for p in sorted(glob.glob(str(base / name)))]
            if paths:
                found += [p for p in paths if p.resolve().is_relative_to(REPO.resolve())]
                break
    return [p for p in found if not is_prose(p)]


def is_prose(path: Path) -> bool:
    rel = path.resolve().relative_to(REPO.resolve()).as_posix()
    return path.name == "README.md" or rel in PROSE


def source_numbers(paths: list[Path]) -> set[float]:
    """Every number written in the cited files (folders: their text files)."""
    values: set[float] = set()
    for path in paths:
        files = [f for f in path.rglob("*") if f.suffix in TEXT_SUFFIXES and not is_prose(f)] if path.is_dir() \
            else [path] if path.suffix in TEXT_SUFFIXES else []
        for f in files:
            text = f.read_text(encoding="utf-8", errors="replace")
            values.update(float(m.group()) for m in _SOURCE_NUMBER.finditer(re.sub(r"(?<=\d),(?=\d{3})", "", text)))
    return values


def quoted_numbers(text: str) -> list[re.Match]:
    """The numbers of a block that must have a source (module doc: what is not looked up)."""
    for pattern, replacement in _SKIPPED:
        text = pattern.sub(replacement, text)
    return [m for m in _NUMBER.finditer(text) if not m.group("approx")]


def has_source(m: re.Match, values: set[float]) -> bool:
    """A source number rounds to the quoted one at the prose's precision (module doc)."""
    digits = m.group("int").replace(",", "") + (m.group("frac") or "")
    unit = 10.0 ** -(len(m.group("frac") or ".") - 1)
    scale = 10.0 ** int(m.group("exp")[1:]) if m.group("exp") else 1.0
    scale *= 1000.0 if m.group("k") else 1.0
    quoted = float(digits) * scale
    forms = [(quoted, unit * scale)] + ([(quoted / 100, unit * scale / 100)] if m.group("pct") is not None else [])
    return any(abs(abs(v) - q) <= 0.5 * u * (1 + 1e-9) for v in values for q, u in forms)


@dataclass
class Checked:
    doc: str
    blocks: list[tuple[Block, list[Path]]]


def checked_blocks(rel: str, cumulative: bool, select=None) -> Checked:
    """The blocks of document `rel` that are checked, each with the sources it may use."""
    doc = REPO / rel
    out = []
    for section in blocks(doc.read_text(encoding="utf-8"), doc):
        cited: list[Path] = []
        for block in section:
            cited = (cited if cumulative else []) + block.cites
            if select is None or select(block):
                out.append((block, list(cited)))
    return Checked(rel, out)


def unsourced(checked: Checked) -> list[str]:
    """`doc:line: number (in "...") not in <sources>` for every quoted number without a source."""
    problems = []
    for block, sources in checked.blocks:
        if block.unchecked is not None:
            continue
        values = source_numbers(sources)
        for m in quoted_numbers(block.text):
            if not has_source(m, values):
                line = block.line + block.text[: m.start()].count("\n")
                context = " ".join(block.text.split())[:90]
                names = ", ".join(p.resolve().relative_to(REPO.resolve()).as_posix() for p in sources) or "no source cited"
                problems.append(f"{checked.doc}:{line}: {m.group().strip()} (in {context!r}...) not in {names}")
    return problems


# ------------------------------------------------------------------------------------------ the documents
@functools.lru_cache(maxsize=1)
def _readme_spans() -> tuple[tuple[int, int], ...]:
    """Line spans of the README that quote results: its Results section (the generated table is held
    equal to its records by tests/test_headline.py; the words around it are checked here)."""
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    results = lines.index("## Results") + 1
    after = next(i for i in range(results, len(lines)) if lines[i].startswith("## ")) + 1
    return ((results, after),)


def _readme_results(block: Block) -> bool:
    return any(start <= block.line < end for start, end in _readme_spans())


DOCUMENTS = {
    "docs/results/README.md": lambda: checked_blocks("docs/results/README.md", cumulative=True),
    "README.md": lambda: checked_blocks("README.md", cumulative=False, select=_readme_results),
}


@pytest.mark.parametrize("doc", sorted(DOCUMENTS))
def test_every_quoted_number_has_a_source_in_a_cited_committed_file(doc):
    checked = DOCUMENTS[doc]()
    assert checked.blocks, f"{doc}: nothing checked"
    problems = unsourced(checked)
    assert not problems, f"{len(problems)} quoted number(s) without a source:\n" + "\n".join(problems)


def test_opting_out_is_rare_and_says_why():
    markers = [(doc, m.group(2).strip()) for doc in DOCUMENTS
               for m in _MARKER.finditer((REPO / doc).read_text(encoding="utf-8"))]
    assert all(reason for _, reason in markers), [doc for doc, reason in markers if not reason]
    assert len(markers) <= MAX_UNCHECKED, markers


def test_the_readme_results_blocks_each_cite_a_generated_source():
    for block, sources in DOCUMENTS["README.md"]().blocks:
        if quoted_numbers(block.text) and block.unchecked is None:
            assert sources, f"README.md:{block.line}: quotes numbers but cites no report or JSON"


# ------------------------------------------------------------------------------------ the checker itself
def _check(text: str, tmp_path: Path, source: str) -> list[str]:
    (tmp_path / "src.md").write_text(source)
    doc = tmp_path / "doc.md"
    doc.write_text(text)
    out = []
    for section in blocks(text, doc):
        cited: list[Path] = []
        for block in section:
            cited += block.cites
            if block.unchecked is None:
                out += [m.group().strip() for m in quoted_numbers(block.text) if not has_source(m, source_numbers(cited))]
    return out


def test_the_checker_on_planted_numbers(tmp_path, monkeypatch):
    monkeypatch.setattr(f"{__name__}.REPO", tmp_path)  # the planted files are the repository
    source = "| arm | 0.0566 [0.0523, 0.0594] | 1100 | 29,491,200 env steps | 0.268 | 530123 | -0.00881 |"
    cite = "[report](src.md)"
    assert _check(f"{cite}: failure 0.057 [0.052, 0.059], 1100 iterations, 2.95e7 steps, 26.8%, 530k, -0.009",
                  tmp_path, source) == []
    assert _check(f"{cite}: failure 0.058 and 1200 iterations, 29% (27% is 0.268 rounded)", tmp_path, source) == ["0.058", "1200", "29%"]
    assert _check("no citation: 0.0566", tmp_path, source) == ["0.0566"]  # a number needs a cited file
    assert _check(f"{cite}\n\nlater in the section: 1100", tmp_path, source) == []  # cited above in its section
    assert _check(f"{cite}\n\n## next section\n\n1100", tmp_path, source) == ["1100"]  # not across sections
    assert _check(f"{cite}: `max_iterations=4242`, 2026-11-27, commit 8d82203, issue 47, ~945 s, about 89%",
                  tmp_path, source) == []
    assert _check(f"<!-- numbers unchecked: a record -->\n{cite}: 4242\n\nstill checked: 4242", tmp_path,
                  source) == ["4242"]
    (tmp_path / "README.md").write_text("prose 4242")
    assert _check("[prose](README.md): 4242", tmp_path, source) == ["4242"]  # prose is never a source
