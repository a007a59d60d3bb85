"""An ONNX policy found in a run folder belongs to that run: sim2sim writes its results under the run and
compares them with the run's own MuJoCo-Warp evaluation, so a policy copied there from another run
(another motion, control rate or bins, or an iteration the run never reached) is refused, as eval and
export refuse a checkpoint of another task. Read from the run's record only (numpy-free JSON): the
motion's segments, the resolved config and the status.
"""

from __future__ import annotations

import math
from pathlib import Path

from bmimic.runs.folder import MOTION_SEGMENTS, read_json, read_resolved_config, read_status
from bmimic.runs.schema import ITERATION
from bmimic.sim2sim.spec import PolicySpec, Sim2SimError

TOLERANCE = 1e-6
"""Relative slack on times and rates written through text (JSON, ONNX metadata strings)."""


def _close(a, b) -> bool:
    try:
        return math.isclose(float(a), float(b), rel_tol=TOLERANCE, abs_tol=TOLERANCE)
    except (TypeError, ValueError):
        return False


def differences(spec: PolicySpec, run_dir: Path) -> list[str]:
    """How the policy's metadata differs from the run's record (empty: the policy can be this run's)."""
    out = []
    segments = read_json(Path(run_dir) / MOTION_SEGMENTS)
    if isinstance(segments, list) and all(isinstance(s, dict) for s in segments):
        ours = [(str(s.get("name")), s.get("start_s"), s.get("end_s")) for s in segments]
        theirs = [(str(s.name), s.start_s, s.end_s) for s in spec.segments]
        if len(ours) != len(theirs) or any(a[0] != b[0] or not (_close(a[1], b[1]) and _close(a[2], b[2]))
                                           for a, b in zip(ours, theirs)):
            out.append(f"motion segments ({len(theirs)} ending at {theirs[-1][2] if theirs else 0:g} s, the run's "
                       f"{len(ours)} ending at {ours[-1][2] if ours else 0} s)")
    config = read_resolved_config(run_dir) or {}
    sim, sampler = config.get("sim") or {}, config.get("sampler") or {}
    for name, mine, given in (("sim.timestep_s", sim.get("timestep_s"), spec.physics_dt_s),
                             ("sim.decimation", sim.get("decimation"), spec.decimation)):
        if mine is not None and not _close(mine, given):
            out.append(f"{name} ({given:g}, the run's {mine})")
    if sampler.get("bins") is not None and str(sampler.get("bins")) != spec.bin_layout:
        out.append(f"sampler.bins ({spec.bin_layout}, the run's {sampler.get('bins')})")
    elif spec.bin_layout == "time" and sampler.get("bin_size_seconds") is not None and not _close(
            sampler.get("bin_size_seconds"), spec.bin_size_s):
        out.append(f"sampler.bin_size_seconds ({spec.bin_size_s:g}, the run's {sampler.get('bin_size_seconds')})")
    reached = read_status(run_dir).get(ITERATION)
    if spec.iteration is not None and isinstance(reached, int) and spec.iteration > reached:
        out.append(f"iteration {spec.iteration} (the run reached {reached})")
    return out


def check_policy_of_run(spec: PolicySpec, run_dir: Path | None) -> None:
    """Sim2SimError (one line) when the policy found in `run_dir` cannot be that run's (see differences)."""
    if run_dir is None:
        return
    differ = differences(spec, run_dir)
    if differ:
        raise Sim2SimError(f"{spec.path}: was exported from another run than {run_dir}: {'; '.join(differ[:3])}; "
                           "evaluate it in its own run folder, or copy it out of this one to evaluate it alone")
