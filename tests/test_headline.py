"""The README's results table is the one `python -m analysis.headline` builds from the committed records
(issue 75): a record that changes changes the table, and a hand edit of the table fails here."""

from __future__ import annotations

import json
import shutil

import pytest

from analysis import bench_index, headline
from analysis.generated_block import block_between, replace_between
from tests.conftest import REPO


def test_the_readme_table_is_the_one_the_records_give():
    readme = (REPO / "README.md").read_text()
    assert headline.readme_table(readme) == headline.headline_table(REPO), (
        "README.md's results table differs from its records: run python -m analysis.headline --write")


def test_a_changed_record_changes_its_row(tmp_path):
    """A planted answer: copy the confirmatory study's records, move one seed's final failure, and the
    row's mean moves by a tenth of the change (10 seeds)."""
    study = "docs/results/confirm_hybrid_dance1/runs"
    shutil.copytree(REPO / study, tmp_path / study, ignore=shutil.ignore_patterns("*.parquet", "*.png"))
    before = headline.final_failures(tmp_path, "confirm_hybrid_dance1", "adaptive_hybrid")
    metrics = tmp_path / study / "motion=lafan_dance1_full,sampler=adaptive_hybrid" / "seed=10" / "metrics.json"
    data = json.loads(metrics.read_text())
    data["final_eval_failure_rate"] += 0.1
    metrics.write_text(json.dumps(data))
    after = headline.final_failures(tmp_path, "confirm_hybrid_dance1", "adaptive_hybrid")
    assert sum(after.values()) / 10 == pytest.approx(sum(before.values()) / 10 + 0.01)
    row = headline.hybrid_vs_design(tmp_path)
    assert f"{sum(after.values()) / 10:.4f}" in row.numbers


def test_the_markers_are_required():
    with pytest.raises(ValueError, match="markers"):
        headline.readme_table("# a README without the table\n")
    text = f"x\n{headline.BEGIN}\n| a |\n{headline.END}\ny\n"
    assert headline.readme_table(text) == "| a |\n"


def test_write_replaces_a_stale_table_and_says_so(tmp_path, monkeypatch, capsys):
    """--write once printed "rewritten" and left README.md as it was (its markers' newline counted twice)."""
    stale = f"# x\n{headline.BEGIN}\n| old |\n{headline.END}\nafter\n"
    (tmp_path / "README.md").write_text(stale)
    monkeypatch.setattr(headline, "REPO", tmp_path)
    monkeypatch.setattr(headline, "headline_table", lambda repo=None: "| new |\n")
    assert headline.main(["--write"]) == 0 and "rewritten" in capsys.readouterr().out
    assert (tmp_path / "README.md").read_text() == f"# x\n{headline.BEGIN}\n| new |\n{headline.END}\nafter\n"
    assert headline.main(["--write"]) == 0 and "unchanged" in capsys.readouterr().out
    assert headline.main(["--check"]) == 0


def test_the_benchmarks_records_index_is_the_one_the_files_give():
    doc = (REPO / bench_index.DOC).read_text()
    committed = block_between(doc, bench_index.BEGIN, bench_index.END, bench_index.DOC)
    assert committed == bench_index.bench_index(REPO), "run python -m analysis.bench_index --write"
    names = [line.split("`")[1] for line in committed.splitlines()[2:]]
    assert sorted(names) == sorted(p.name for p in (REPO / "docs" / "bench").glob("*.json"))


def test_a_record_is_found_by_its_full_name_its_tail_or_a_glob():
    name = "2026-12-01_h200_race_1x4096-uniform-s0.json"
    assert bench_index._cites(f"see `docs/bench/{name}`", name)
    assert bench_index._cites("and `..._1x8192-hybrid-s1.json`", "2026-12-01_h200_race_1x8192-hybrid-s1.json")
    assert bench_index._cites("`docs/bench/2026-11-22_h100_s4_*.json`", "2026-11-22_h100_s4_default.json")
    assert not bench_index._cites("`..._1x8192-hybrid-s1.json`", "2026-12-01_h200_race_2x8192-hybrid-s1.json")


def test_a_generated_block_is_replaced_and_nothing_else():
    doc = "intro\n<!-- b -->\nold\nrows\n<!-- e -->\ntail <!-- b --> is not here\n"
    with pytest.raises(ValueError, match="doc.md"):  # BEGIN twice
        replace_between(doc, "<!-- b -->", "<!-- e -->", "new\n", "doc.md")
    doc = "intro\n<!-- b -->\nold\nrows\n<!-- e -->\ntail\n"
    new = replace_between(doc, "<!-- b -->", "<!-- e -->", "\nnew\n\n", "doc.md")
    assert new == "intro\n<!-- b -->\nnew\n<!-- e -->\ntail\n"
    assert block_between(new, "<!-- b -->", "<!-- e -->", "doc.md") == "new\n"
    with pytest.raises(ValueError, match="out of order"):
        block_between("<!-- e -->\n<!-- b -->\n", "<!-- b -->", "<!-- e -->", "doc.md")
