"""The one guarded way bmimic reads a text file it did not just write (a run's JSON and YAML records,
a checkpoint's config string, bench and race records): it cannot hang, recurse without bound or expand
without bound.

- `read_text`: regular files only. The open never blocks (O_NONBLOCK: a FIFO opens at once and is then
  refused by its type), a device or a link to one is refused by the type of what was opened, and a
  file over `max_bytes` is refused before it is read.
- `parse_json`: nesting deeper than MAX_DEPTH is refused before the parser recurses; with `finite`,
  so is a number that is not finite (NaN, Infinity, 1e999: bmimic writes none, see atomic_write_json).
- `regular_file`: the same type check for a binary reader that opens a file by name (torch.load,
  pyarrow, onnxruntime), and with `within`, a link out of the run folder refused.
- `parse_yaml`: YAML's safe loader, with documents of more than MAX_NODES nodes once their aliases are
  expanded refused before they are built (an alias bomb expands exponentially in whoever copies it next).
Each raises `UnsafeFileError` (a ValueError, so the readers' existing `except (OSError, ValueError)`
keeps treating such a file as unreadable) with one line naming the file.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import Any

MAX_BYTES = 64 * 2**20
"""Largest record read (the largest legitimate ones, bench records and resolved configs, are < 1 MB)."""
MAX_DEPTH = 64
"""Deepest nesting of brackets accepted in a JSON record (bmimic's own go 6 deep)."""
MAX_NODES = 1_000_000
"""Most YAML nodes in one document once its aliases are expanded (a run's config has ~2,000)."""


class UnsafeFileError(ValueError):
    """A file refused by the guarded reader (not a regular file, too large, too deep, an alias bomb)."""


def _open_regular(path: str | os.PathLike) -> tuple[int, os.stat_result]:
    """An fd and the stat of the regular file at `path`, opened without blocking (a FIFO opens at once);
    UnsafeFileError (fd closed) when it is not a regular file."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise UnsafeFileError(f"{path}: not a regular file (a FIFO, a device or a link to one)")
    except BaseException:
        os.close(fd)
        raise
    return fd, info


def regular_file(path: str | os.PathLike, within: str | os.PathLike | None = None) -> Path:
    """`path`, once checked for a reader that opens it by name (torch.load, pyarrow, onnxruntime), which
    would block on a FIFO or read a device forever: a regular file (links followed), and with `within`
    (a run folder) one whose real path lies inside that folder, so that a run's checkpoint or table is
    never another run's or the machine's. OSError when absent, UnsafeFileError otherwise."""
    fd, _ = _open_regular(path)
    os.close(fd)
    if within is not None:
        real, root = Path(path).resolve(), Path(within).resolve()
        if not real.is_relative_to(root):
            raise UnsafeFileError(f"{path}: links to {real}, outside its run folder {within} (a run's files are its "
                                  "own: copy the file in instead of linking it)")
    return Path(path)


def read_text(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> str:
    """The UTF-8 text of the regular file at `path`; OSError when absent or unreadable, UnsafeFileError
    when it is not a regular file (a FIFO, a device, a link to one) or larger than `max_bytes`."""
    fd, info = _open_regular(path)
    try:
        if info.st_size > max_bytes:
            raise UnsafeFileError(f"{path}: {info.st_size} bytes, more than the {max_bytes} a record may have")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(max_bytes + 1)
    finally:
        os.close(fd)
    if len(data) > max_bytes:  # grew while read
        raise UnsafeFileError(f"{path}: more than the {max_bytes} bytes a record may have")
    return data.decode("utf-8")


def nesting_depth(text: str) -> int:
    """The deepest nesting of JSON brackets in `text`, strings skipped (linear, no recursion)."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def parse_json(text: str, what: str | os.PathLike = "JSON", max_depth: int = MAX_DEPTH, finite: bool = False) -> Any:
    """`json.loads(text)`, refusing nesting deeper than `max_depth` and, with `finite`, any number that is
    not finite (UnsafeFileError naming `what`): a record whose numbers are measurements, where NaN or
    Infinity would pass a `> 0` check and then be written back as null."""
    if text.count("[") + text.count("{") > max_depth and nesting_depth(text) > max_depth:
        raise UnsafeFileError(f"{what}: nested deeper than {max_depth} levels")

    def not_finite(word: str) -> float:
        raise UnsafeFileError(f"{what}: holds the number {word}, which is not finite")

    def number(word: str) -> float:
        value = float(word)
        return value if math.isfinite(value) else not_finite(word[:40])
    hooks: dict[str, Any] = {"parse_constant": not_finite, "parse_float": number} if finite else {}
    try:
        return json.loads(text, **hooks)
    except RecursionError:  # a depth the scan did not see (it cannot happen; never a traceback)
        raise UnsafeFileError(f"{what}: nested too deep") from None


def read_json(path: str | os.PathLike, max_bytes: int = MAX_BYTES, finite: bool = False) -> Any:
    """The parsed JSON record at `path` (read_text, then parse_json)."""
    return parse_json(read_text(path, max_bytes), path, finite=finite)


def check_yaml(text: str, what: str | os.PathLike = "YAML", max_nodes: int = MAX_NODES) -> str:
    """`text`, after scanning its YAML events (nothing is built): UnsafeFileError naming `what` for a
    document of more than `max_nodes` nodes once its aliases are expanded (an alias bomb: 70 aliases can
    stand for 10**8 nodes), nesting deeper than MAX_DEPTH, or text that is not YAML."""
    import yaml

    sizes: dict[str, int] = {}  # anchor -> expanded nodes of the node it names
    counts: list[int] = [0]  # per open collection (the document first): expanded nodes so far
    anchors: list[str | None] = [None]  # and its anchor

    def add(n: int) -> None:
        counts[-1] += n
        if counts[-1] > max_nodes:
            raise UnsafeFileError(f"{what}: more than {max_nodes} YAML nodes once its aliases are expanded "
                                  "(an alias bomb?)")
    try:
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.ScalarEvent):
                if event.anchor:
                    sizes[event.anchor] = 1
                add(1)
            elif isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                counts.append(1)
                anchors.append(event.anchor)
                if len(counts) > MAX_DEPTH + 1:
                    raise UnsafeFileError(f"{what}: nested deeper than {MAX_DEPTH} levels")
            elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                count, anchor = counts.pop(), anchors.pop()
                if anchor:
                    sizes[anchor] = count
                add(count)
            elif isinstance(event, yaml.AliasEvent):
                add(sizes.get(event.anchor, 1))
    except yaml.YAMLError as e:
        raise UnsafeFileError(f"{what}: not valid YAML ({str(e).splitlines()[0]})") from None
    return text


def parse_yaml(text: str, what: str | os.PathLike = "YAML") -> Any:
    """`yaml.safe_load(text)` of a document `check_yaml` accepts."""
    import yaml

    return yaml.safe_load(check_yaml(text, what))


def read_yaml_text(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> str:
    """The text of the YAML record at `path`, read and checked (for OmegaConf.create, whose loader
    reads numbers as Hydra wrote them)."""
    return check_yaml(read_text(path, max_bytes), path)


def read_yaml(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> Any:
    """The parsed YAML record at `path` (read_text, then parse_yaml)."""
    return parse_yaml(read_text(Path(path), max_bytes), path)


__all__ = ["MAX_NODES", "MAX_BYTES", "MAX_DEPTH", "UnsafeFileError", "check_yaml", "nesting_depth", "parse_json",
           "parse_yaml", "read_json", "read_text", "read_yaml", "read_yaml_text", "regular_file"]
