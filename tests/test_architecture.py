"""The architecture rules of docs/architecture.md, read from the source (ast; nothing is imported):

- no import cycles among the modules of bmimic and analysis;
- no entry point imports another entry point (they share code through non-entry modules);
- nothing in bmimic imports analysis (the producer never depends on its consumer);
- bmimic.task is the one composition root: the only module that constructs the environment, the
  evaluator and the trainer;
- entry points use public interfaces only (no `obj._private` of other modules' objects);
- bmimic.runs.folder and the analysis are torch-free (checked by importing them in a fresh process), and
  every bmimic module the analysis reaches (imports, lazy ones included) names no torch import;
- no string literal spells a measured, progress or failure column of the run schema (bmimic.runs.schema)
  outside it, and none names the key columns (`iteration`, `bin`) where a column or record key is named;
- run-folder tables are written through bmimic.runs.record only: no other module names the table writers
  (atomic_write_parquet, atomic_write_csv), and evaluation's producers (bmimic.eval, bmimic.evaluation,
  bmimic.sim2sim) name no atomic writer at all;
- every module is on a floor of docs/architecture.md's floor table, and every import goes down the
  floors or stays on its floor (a lower floor never imports a higher one: the env hands the sampler's
  feedback what it measured);
- every run-folder file name is spelled in bmimic.runs.folder only;
- no module is over 400 lines.

Imports inside functions count: a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from bmimic.runs import schema as run_schema
from tests.conftest import REPO

PACKAGES = ("bmimic", "analysis")
MAX_LINES = 400

ENTRY_POINTS = ("bmimic.train", "bmimic.race", "bmimic.eval", "bmimic.play", "bmimic.bench", "bmimic.export", "bmimic.state",
                "bmimic.sim2sim",
                "bmimic.launch", "bmimic.motion.convert", "bmimic.motion.example", "analysis.report", "analysis.index",
                "analysis.headline", "analysis.bench_index", "analysis.races", "analysis.race_whole_clip", "analysis.compact")
"""The command lines (`python -m <name>`); a package entry point (sim2sim) is all of its modules."""

COMPOSITION_ROOT = "bmimic.task"
CONSTRUCTED_ONLY_BY_THE_ROOT = ("TrackingEnv", "Evaluator", "Trainer")
"""(Samplers are built by the sampling package's factory, which task.py calls for runs; the sampling
benchmark, which runs samplers without an environment, calls it too.)"""

@dataclass
class Module:
    name: str
    path: Path
    tree: ast.Module
    lines: int


def _modules() -> dict[str, Module]:
    found = {}
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            text = path.read_text(encoding="utf-8")
            found[".".join(parts)] = Module(".".join(parts), path, ast.parse(text, str(path)), len(text.splitlines()))
    return found


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The module of ours a dotted import name refers to (its longest known prefix), else None."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _imports(module: Module) -> set[str]:
    """Our modules that `module` imports anywhere (top level, functions, TYPE_CHECKING blocks)."""
    out = set()
    is_package = module.path.name == "__init__.py"
    for node in ast.walk(module.tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.name.split(".") if is_package else module.name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                origin = ".".join(base + ([node.module] if node.module else []))
            else:
                origin = node.module or ""
            # `from pkg import mod` imports the module pkg.mod; `from mod import name` the module mod.
            targets = [f"{origin}.{a.name}" if f"{origin}.{a.name}" in MODULES else origin for a in node.names]
        else:
            continue
        out |= {t for t in map(_resolve, targets) if t and t != module.name}
    return out


GRAPH = {name: _imports(m) for name, m in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def _entry_point(module: str) -> str | None:
    return next((e for e in ENTRY_POINTS if module == e or module.startswith(e + ".")), None)


# --------------------------------------------------------------------------------------------- the helpers
def test_the_cycle_finder_finds_planted_cycles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a", "e"}, "e": {"d"}, "f": set()}
    assert sorted(_cycles(graph)) == [["a", "b", "c"], ["d", "e"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_reader_sees_lazy_relative_and_from_imports():
    assert "bmimic.task" in GRAPH["bmimic.job"]  # a top-level `from bmimic.task import ...`
    assert "bmimic.training.policy" in GRAPH["bmimic.eval"]  # inside a function
    assert "bmimic.sampling.config" in GRAPH["bmimic.sampling"]  # the package's __init__
    assert all(e in MODULES for e in ENTRY_POINTS)


# --------------------------------------------------------------------------------------------- the rules
def test_no_import_cycles():
    assert _cycles(GRAPH) == []


def test_no_entry_point_imports_another():
    crossing = sorted((a, b) for a, targets in GRAPH.items() for b in targets
                      if _entry_point(a) and _entry_point(b) and _entry_point(a) != _entry_point(b))
    assert crossing == []


def test_nothing_in_bmimic_imports_analysis():
    assert sorted((a, b) for a, targets in GRAPH.items() if a.startswith("bmimic")
                  for b in targets if b.startswith("analysis")) == []


def test_only_the_composition_root_constructs_envs_evaluators_and_trainers():
    calls = []
    for name, module in MODULES.items():
        for node in ast.walk(module.tree):
            if isinstance(node, ast.Call):
                f = node.func
                called = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
                if called in CONSTRUCTED_ONLY_BY_THE_ROOT and name != COMPOSITION_ROOT:
                    calls.append((name, called, node.lineno))
    assert calls == []


def test_entry_points_use_public_interfaces_only():
    private = []
    for name, module in MODULES.items():
        if not _entry_point(name):
            continue
        for node in ast.walk(module.tree):
            if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                    and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
                private.append((name, ast.unparse(node), node.lineno))
    assert private == []


@pytest.mark.parametrize("module", ["bmimic.runs.folder", "analysis.report", "analysis.index"])
def test_run_folder_and_analysis_are_torch_free(module):
    code = f"import sys, {module}; assert 'torch' not in sys.modules, 'torch imported'"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]


def test_no_module_over_400_lines():
    over = {name: m.lines for name, m in MODULES.items() if m.lines > MAX_LINES}
    assert over == {}


def _imports_torch(module: Module) -> bool:
    for node in ast.walk(module.tree):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if isinstance(
            node, ast.ImportFrom) and not node.level else []
        if any(n == "torch" or n.startswith("torch.") for n in names):
            return True
    return False


def test_analysis_reaches_only_torch_free_bmimic_modules():
    reached, todo = set(), [m for m in MODULES if m.startswith("analysis")]
    while todo:
        for target in GRAPH[todo.pop()]:
            if target not in reached:
                reached.add(target)
                todo.append(target)
    assert sorted(m for m in reached if m.startswith("bmimic") and _imports_torch(MODULES[m])) == []


SCHEMA_NAMES = {*run_schema.ERROR_COLUMNS, *run_schema.SMOOTHNESS_COLUMNS, run_schema.TRACKED_THROUGH,
                run_schema.ENV_STEPS, run_schema.WALL_TIME_S, run_schema.FAILURE_RATE, run_schema.HORIZON_TRUNCATED}
"""The measured columns and the progress and failure columns: spelled in bmimic.runs.schema only, used
through its names everywhere else."""

KEY_NAMES = {run_schema.ITERATION, run_schema.BIN}
"""The key columns: plain words ("bin" is an axis label and a word of the report's prose, "iteration" a
value of sampler.accounting.update_every), so they are held to the rule where they name a column or a
record key (`column_positions`), not wherever the word occurs."""

COLUMN_METHODS = {"sort_values", "groupby", "set_index", "pivot", "pivot_table", "drop", "drop_duplicates",
                  "merge", "get", "pop", "melt", "nunique", "value_counts", "rename", "reindex", "filter"}
COLUMN_KEYWORDS = {"by", "on", "columns", "index", "values", "subset", "left_on", "right_on", "id_vars",
                   "value_vars", "x", "y", "hue"}


def _constants(node: ast.AST) -> list[ast.Constant]:
    """A string constant, or the string constants of a list / tuple / set display."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node]
    if isinstance(node, (ast.List, ast.Tuple, ast.Set)):
        return [c for e in node.elts for c in _constants(e)]
    return []


COLUMN_LISTS = re.compile(r"(?i)(^|_)(cols|columns)$")
"""Names of variables that hold a list of columns (`columns = [...]`, `REQUIRED_COLUMNS = {t: [...]}`)."""


def column_positions(tree: ast.AST) -> list[ast.Constant]:
    """String constants in the places where a table's column or a record's key is named: a subscript
    (`df["bin"]`, `df[["iteration", "bin"]]`), a key of a dict display, an argument of a table or dict
    method that takes column names (`sort_values`, `groupby`, `get`, ...), the name given to
    `df.insert(loc, name, ...)`, a keyword of `df.assign(name=...)` (as a constant at its line), a column
    keyword (`on=`, `columns=`, ...), the left side of `in df.columns`, and the list (or the dict
    values' lists) assigned to a variable named for columns (`cols`, `columns`, `*_COLUMNS`)."""
    found: list[ast.Constant] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript):
            found += _constants(node.slice)
        elif isinstance(node, ast.Dict):
            found += [c for k in node.keys if k is not None for c in _constants(k)]
        elif isinstance(node, ast.Call):
            if isinstance(node.func, ast.Attribute) and node.func.attr in COLUMN_METHODS:
                found += [c for a in node.args for c in _constants(a)]
            if isinstance(node.func, ast.Attribute) and node.func.attr == "insert" and len(node.args) >= 3:
                found += _constants(node.args[1])
            if isinstance(node.func, ast.Attribute) and node.func.attr == "assign":
                found += [ast.Constant(k.arg, lineno=node.lineno) for k in node.keywords if k.arg is not None]
            found += [c for k in node.keywords if k.arg in COLUMN_KEYWORDS for c in _constants(k.value)]
        elif isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and COLUMN_LISTS.search(t.id) for t in targets):
                values = node.value.values if isinstance(node.value, ast.Dict) else [node.value]
                found += [c for v in values for c in _constants(v)]
        elif (isinstance(node, ast.Compare) and isinstance(node.ops[0], (ast.In, ast.NotIn))
              and isinstance(node.comparators[0], ast.Attribute) and node.comparators[0].attr == "columns"):
            found += _constants(node.left)
    return found


def test_measured_columns_are_spelled_only_in_the_run_schema():
    spelled = sorted((name, node.value, node.lineno) for name, module in MODULES.items() if name != "bmimic.runs.schema"
                     for node in ast.walk(module.tree)
                     if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in SCHEMA_NAMES)
    assert spelled == []


def test_key_columns_are_named_through_the_run_schema():
    spelled = sorted((name, node.value, node.lineno) for name, module in MODULES.items() if name != "bmimic.runs.schema"
                     for node in column_positions(module.tree) if node.value in KEY_NAMES)
    assert spelled == []


def test_column_positions_finds_the_places_a_column_is_named():
    tree = ast.parse('df["bin"]; df[["iteration", "x"]]; {"bin": 1}; df.sort_values("iteration"); '
                     'df.merge(o, on=["bin"]); s.get("iteration"); "bin" in df.columns; '
                     'df.insert(0, "iteration", v); df.assign(bin=b, x=1); cols = ["x", "bin"]; '
                     'REQUIRED_COLUMNS = {"t": ["iteration", "x"]}; choices = ["bin", "iteration"]; '
                     'ax.set_xlabel("bin"); cfg.update_every == "iteration"; f"{n} bin"; xs.insert(0, "bin")')
    assert sorted(c.value for c in column_positions(tree) if c.value in KEY_NAMES) == sorted([
        "bin", "iteration", "bin", "iteration", "bin", "iteration", "bin", "iteration", "bin", "bin", "iteration"])


FLOOR_TABLE_HEADER = "| floor | modules | their job |"


def drawn_floors(text: str) -> list[tuple[str, list[str]]]:
    """(floor, names) of each row of the floor table in docs/architecture.md, top floor first."""
    lines = text.splitlines()
    start = lines.index(FLOOR_TABLE_HEADER) + 2  # past the header and its |---| line
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        floor, names, _ = (cell.strip() for cell in line.strip("|").split("|"))
        rows.append((floor, re.findall(r"`([^`]+)`", names)))
    return rows


def drawn_module(name: str) -> str:
    """The module a drawn name stands for: `bmimic.<name>` unless it is the analysis's; `__init__` is bmimic."""
    name = name.rstrip("/")
    return "bmimic" if name == "__init__" else name if name.split(".")[0] == "analysis" else f"bmimic.{name}"


FLOORS = drawn_floors((REPO / "docs" / "architecture.md").read_text(encoding="utf-8"))


def floor_of(module: str) -> int | None:
    """The height of `module`'s floor (0: the bottom one): the floor of its longest drawn name, where a
    name ending in `/` is a package and all its modules and any other name one module."""
    best = None
    for height, (_, names) in enumerate(reversed(FLOORS)):
        for name in names:
            drawn = drawn_module(name)
            if (module == drawn or name.endswith("/") and module.startswith(drawn + ".")) and (
                    best is None or len(drawn) > best[0]):
                best = (len(drawn), height)
    return None if best is None else best[1]


def upward_imports(graph: dict[str, set[str]]) -> list[tuple[str, str, str, str]]:
    """(module, its floor, imported module, its floor) of every import that goes up the floors."""
    name = [floor for floor, _ in reversed(FLOORS)]
    return sorted((a, name[floor_of(a)], b, name[floor_of(b)]) for a, targets in graph.items() for b in targets
                  if floor_of(b) > floor_of(a))


def test_the_floor_table_is_read_as_drawn():
    heights = [floor_of(m) for m in ("bmimic.robot.models.g1", "bmimic.motion.motion", "bmimic.sim.simulator",
                                     "bmimic.sampling.bins", "bmimic.envs.tracking_env", "bmimic.training.runner",
                                     "bmimic.task", "bmimic.evaluation.saved_run", "bmimic.train")]
    assert heights == sorted(heights) and len(set(heights)) == len(heights)
    assert floor_of("bmimic.sweeping.gpu_slots") == 0 < floor_of("bmimic.sweeping.jobs")  # the longest name wins
    assert floor_of("bmimic") == floor_of("bmimic.runs.folder") == 0
    # The command lines are on top; the CSV converter is also the motion floor's (load_motion uses it).
    assert [e for e in ENTRY_POINTS if floor_of(e) != len(FLOORS) - 1] == ["bmimic.motion.convert"]
    assert upward_imports({"bmimic.robot.models.g1": {"bmimic.task"}, "bmimic.task": {"bmimic.robot.models.g1"}}) == [
        ("bmimic.robot.models.g1", "robot", "bmimic.task", "composition")]


def test_every_module_is_drawn_on_a_floor_and_every_drawn_name_exists():
    assert sorted(m for m in MODULES if floor_of(m) is None) == []
    names = [n for _, floor in FLOORS for n in floor]
    assert sorted(n for n in names if not any(m == drawn_module(n) or m.startswith(drawn_module(n) + ".")
                                              for m in MODULES)) == []
    assert sorted({n for n in names if names.count(n) > 1}) == []


def test_every_import_goes_down_the_floors_or_stays_on_its_floor():
    assert upward_imports(GRAPH) == []


TABLE_WRITERS = ("atomic_write_parquet", "atomic_write_csv")
TABLE_WRITING_MODULES = ("bmimic.runs.atomic_io", "bmimic.runs.folder", "bmimic.runs.record")
"""atomic_io defines the writers, run_folder re-exports them, run_record writes every run-folder table."""
EVALUATION_PRODUCERS = ("bmimic.eval", "bmimic.evaluation", "bmimic.sim2sim")
"""They write an evaluation's files through bmimic.runs.record.write_evaluation (the summary JSON too)."""


def _writers_named(tree: ast.AST, prefixes: tuple[str, ...]) -> list[tuple[str, int]]:
    """(name, line) of every name, attribute or import in `tree` that starts with one of `prefixes`."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            names = [node.id]
        elif isinstance(node, ast.Attribute):
            names = [node.attr]
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name.rpartition(".")[2] for a in node.names]
        else:
            continue
        found += [(n, node.lineno) for n in names if n.startswith(prefixes)]
    return found


def test_the_writer_finder_sees_calls_attributes_and_imports():
    planted = ast.parse("from bmimic.runs.folder import atomic_write_csv\nimport bmimic.runs.folder as rf\n"
                        "def f(df):\n    atomic_write_csv('a.csv', df)\n"
                        "    rf.atomic_write_parquet('b', df)\n")
    assert sorted(_writers_named(planted, TABLE_WRITERS)) == [
        ("atomic_write_csv", 1), ("atomic_write_csv", 4), ("atomic_write_parquet", 5)]


def test_run_folder_tables_are_written_only_through_the_run_record():
    bypassing = sorted((name, *hit) for name, module in MODULES.items() if name not in TABLE_WRITING_MODULES
                       for hit in _writers_named(module.tree, TABLE_WRITERS))
    assert bypassing == []
    producers = sorted((name, *hit) for name, module in MODULES.items()
                       if any(name == p or name.startswith(p + ".") for p in EVALUATION_PRODUCERS)
                       for hit in _writers_named(module.tree, ("atomic_write", "make_folder")))
    assert producers == []


FILE_SUFFIXES = (".json", ".csv", ".parquet", ".log", ".lock", ".pt", ".onnx")
REPORT_FILES = {("analysis.report_files", "whole_clip_survival.csv")}
"""A report's own file that has a run-folder file's name (it is written into the report folder)."""


def _string_constants(tree: ast.AST) -> list[ast.Constant]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def test_run_folder_file_names_are_spelled_only_in_the_run_folder_module():
    names = {c.value for c in _string_constants(MODULES["bmimic.runs.folder"].tree)
             if c.value.endswith(FILE_SUFFIXES) and "*" not in c.value and "\\" not in c.value}
    assert {"metrics.json", "eval.parquet", "race.json", "index.csv"} <= names
    spelled = sorted((name, c.value, c.lineno) for name, module in MODULES.items() if name != "bmimic.runs.folder"
                     for c in _string_constants(module.tree)
                     if c.value in names and (name, c.value) not in REPORT_FILES)
    assert spelled == []
