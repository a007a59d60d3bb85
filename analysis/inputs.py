"""Checks on a report's inputs before anything is computed: the runs compared as arms share one motion
and one bin layout (or the user says otherwise), a run copied byte for byte is counted once, and the
report's options are in range. Each refusal is an AnalysisError with one line.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

from analysis import AnalysisError
from analysis.run_files import NEEDED_TABLES, config_value
from bmimic.runs import safe_read
from bmimic.runs.folder import table_path
from bmimic.runs.schema import BUDGET_KEYS, ITERATION

BIN_KEYS = ("sampler.bins", "sampler.bin_size_seconds")
"""Config keys that define a run's time bins (with its motion)."""
MIXED_FLAG = "--allow-mixed"


MOTION_CHECK_KEYS = ("motion.check_plausible",)
"""Motion keys that only decide whether a file is refused, never what is trained on: left out of the motion
a run is compared on (so a run written before such a key existed compares with one that records it)."""


def _flat(tree, prefix: str = "") -> dict:
    if isinstance(tree, dict):
        out = {}
        for k, v in tree.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: tree}


def check_comparable(rows: list[dict], allow_mixed: bool = False) -> list[str]:
    """Refuse included runs trained on different motions or bin layouts: their per-bin tables would
    be compared bin number by bin number, and their failure rates measure different tasks; or on
    different budgets (bmimic.runs.schema.BUDGET_KEYS): a smoke run is not a seed of a study, and arms
    compared at equal iterations would be cut to the shortest. With `allow_mixed` the differences are
    returned as notes instead."""
    used = [r for r in rows if r.get("included") and r.get("_cfg")]
    if len(used) < 2:
        return []
    first = used[0]
    notes = []
    for what, keys in (("motion", None), ("bin layout", BIN_KEYS), ("budget", BUDGET_KEYS)):
        def signature(r, _keys=keys):
            cfg = r["_cfg"]
            if _keys is None:
                flat = _flat(cfg.get("motion") or {}, "motion.")
                return {k: v for k, v in flat.items() if k not in MOTION_CHECK_KEYS}
            if _keys is BUDGET_KEYS:  # as trained: a resume that raised max_iterations updated resolved_config.json
                cfg = r.get("_resolved") or cfg
            return {k: config_value(cfg, k) for k in _keys}
        base = signature(first)
        for r in used[1:]:
            other = signature(r)
            differ = sorted(k for k in set(base) | set(other) if _differs(what, k, base.get(k), other.get(k)))
            if differ:
                k = differ[0]
                line = (f"{_name(first)} and {_name(r)} were trained on different {what}s ({k}: "
                        f"{base.get(k)!r} vs {other.get(k)!r})")
                if not allow_mixed:
                    why = ("(per-bin tables match bins by number)" if what != "budget" else
                           "(a smoke run is not a seed of a study, and arms compared at equal iterations would be cut "
                           "to the shortest run)")
                    raise AnalysisError(f"{line}; a report compares arms on one motion, one bin layout and one "
                                        f"training budget {why}; pass {MIXED_FLAG} to compare them anyway")
                notes.append(line)
                break
    return notes


def _differs(what: str, key: str, a, b) -> bool:
    if a == b:
        return False
    # A budget key left null in a composed config (num_envs, max_iterations: the machine's default) is
    # unknown there, not a difference; time_limit_s null means no limit.
    return not (what == "budget" and key != "time_limit_s" and None in (a, b))


def _name(row: dict) -> str:
    """A run's folder with its parent (`<arm>/seed=<s>`, `<run_name>/<stamp>`)."""
    path = Path(row["run_dir"])
    return f"{path.parent.name}/{path.name}"


def mark_copies(rows: list[dict], refuse: bool = True) -> None:
    """A run whose config, overrides and tables are byte-identical to another's (a copied folder) is counted once:
    the later one (by path) is left out with a problem naming the first. A run whose tables are byte-identical to
    another's while the two differ only in their seed (a copy with its seed edited) is refused: two runs never
    train to the same bytes (wall times alone differ), so it would count one run as a second seed of its arm.
    With `refuse` False (a listing that compares nothing: the sweep index) such a run is left out instead."""
    seen: dict[str, str] = {}
    replicas: dict[str, str] = {}
    for r in sorted(rows, key=lambda r: r["run_dir"]):
        if not r.get("included"):
            continue
        tables = hashlib.sha256()
        for name in NEEDED_TABLES:
            path = table_path(r["run_dir"], name)
            try:
                tables.update(safe_read.regular_file(path, r["run_dir"]).read_bytes())
            except (OSError, ValueError) as e:  # replaced since it was found usable
                raise AnalysisError(f"{path}: cannot be read ({e})") from None
        cfg = sorted(_flat(r.get("_cfg") or {}).items())
        overrides = sorted((r.get("_overrides") or {}).items())
        key = hashlib.sha256(repr((cfg, overrides)).encode() + tables.digest()).hexdigest()
        if key in seen:
            r["included"] = False
            r["problem"] = f"its tables are byte-identical to {seen[key]}'s (a copy): counted once"
            continue
        seen[key] = r["run_dir"]
        # the same run but for its seed: the arm's signature without the seed, and the same tables
        arm = repr(([kv for kv in cfg if kv[0] != "seed"], [kv for kv in overrides if kv[0] != "seed"]))
        first = replicas.setdefault(hashlib.sha256(arm.encode() + tables.digest()).hexdigest(), r["run_dir"])
        if first == r["run_dir"]:
            continue
        if not refuse:
            r["included"] = False
            r["problem"] = f"its tables are byte-identical to {first}'s, which differs only in its seed: a copy"
            continue
        raise AnalysisError(f"{r['run_dir']}: its tables ({', '.join(NEEDED_TABLES)}) are byte-identical to {first}'s "
                            f"and the two differ only in their seed ({r.get('seed')}): a copied run with its seed "
                            "edited is not a second seed; remove the copy")


def collapse_duplicate_seeds(rows: list[dict]) -> list[str]:
    """One run per (arm, seed): a seed launched again (a re-run, a run copied and then resumed) is one
    sample, not several, or the report would count one seed as five and draw intervals and p-values
    from it. The run that trained the most iterations (then the last by path: the newest timestamp) is
    kept; the others are left out with a problem naming it. Returns one line per collapsed seed."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r.get("included") and r.get("seed") is not None:
            groups.setdefault((r["arm"], r["seed"]), []).append(r)
    notes = []
    for (arm, seed), group in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), kv[0][1])):
        if len(group) < 2:
            continue
        keep = max(group, key=lambda r: (_iterations(r), r["run_dir"]))
        for r in group:
            if r is not keep:
                r["included"] = False
                r["problem"] = (f"seed {seed} of arm {arm} again (one seed counts once): the report uses "
                                f"{_name(keep)}")
        notes.append(f"arm {arm}: seed {seed} appears in {len(group)} runs; counted once ({_name(keep)}, the one "
                     "that trained longest, then the newest): give each run its own seed")
    return notes


def _iterations(row: dict) -> int:
    value = row.get(ITERATION)
    return int(value) if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) else -1


def check_options(mastery_threshold: float, success_threshold: float, resamples: int, mastery_persist: int) -> None:
    """The report's options: thresholds are rates in (0, 1], resamples a count a bootstrap can use."""
    for flag, value in (("--mastery-threshold", mastery_threshold), ("--success-threshold", success_threshold)):
        if not (math.isfinite(value) and 0 < value <= 1):
            raise AnalysisError(f"{flag} must be a rate in (0, 1], got {value}")
    if not MIN_RESAMPLES <= resamples <= MAX_RESAMPLES:
        raise AnalysisError(f"--resamples must be in [{MIN_RESAMPLES}, {MAX_RESAMPLES}], got {resamples}")
    if mastery_persist < 1:
        raise AnalysisError(f"--mastery-persist must be >= 1, got {mastery_persist}")


MIN_RESAMPLES = 20
"""Fewer bootstrap resamples leave a 95% interval's ends to chance (0 or fewer: nothing to draw)."""
MAX_RESAMPLES = 1_000_000
"""More only costs time (the default is 2,000)."""
