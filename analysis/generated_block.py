"""A generated block of a hand-written document: the text between two marker lines, read and replaced.

The README's headline table and docs/benchmarks.md's records index are rebuilt from the records by a
command and held equal to them by a test; both live between a BEGIN and an END marker, and this is the
one place that finds and replaces such a block (no pandas, no MuJoCo: the commands stay quick).
"""

from __future__ import annotations


def block_between(doc: str, begin: str, end: str, where: str) -> str:
    """The text between ``begin`` and ``end`` (leading and trailing blank lines dropped, one final newline).

    ValueError, naming ``where``, unless each marker occurs exactly once and ``begin`` comes first.
    """
    if doc.count(begin) != 1 or doc.count(end) != 1 or doc.index(begin) > doc.index(end):
        raise ValueError(f"{where}: the generated block's two markers are missing or out of order")
    return doc.split(begin, 1)[1].split(end, 1)[0].strip("\n") + "\n"


def replace_between(doc: str, begin: str, end: str, block: str, where: str) -> str:
    """``doc`` with the text between its markers replaced by ``block`` (markers kept, the rest unchanged).

    ValueError, naming ``where``, when the markers are missing or out of order.
    """
    block_between(doc, begin, end, where)  # the markers' check
    head, rest = doc.split(begin, 1)
    return head + begin + "\n" + block.strip("\n") + "\n" + end + rest.split(end, 1)[1]
