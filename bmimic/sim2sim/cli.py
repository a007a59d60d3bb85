"""`python -m bmimic.sim2sim`: the command line, and a video of one episode."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from bmimic.cli.common import check_output_file, path_arg, user_errors
from bmimic.cli.extras import require_extra
from bmimic.runs.folder import (
    EVAL_TABLES,
    SIM2SIM_DIR,
    SIM2SIM_WHOLE_CLIP,
    SIM2SIM_WHOLE_CLIP_GAP,
    WHOLE_CLIP_SURVIVAL,
)
from bmimic.runs.schema import WHOLE_CLIP_CONDITIONS
from bmimic.sim2sim.gap import GAP_FILE, format_gap
from bmimic.sim2sim.model import build_model, model_label
from bmimic.sim2sim.native_eval import evaluate, locate
from bmimic.sim2sim.rollout import Rollout, run_episode
from bmimic.sim2sim.spec import (
    Sim2SimError,
    clip_frames,
    clip_indices,
    first_line,
    policy_session,
    read_policy,
    read_reference,
)


def render_video(policy_path: Path, run_dir: Path | None, model: str, joint_dynamics: str, out: Path,
                 start_s: float, duration_s: float, width: int = 640, height: int = 480,
                 clip: str | None = None) -> Path:
    """One episode from `start_s` (seconds into `clip`, a library's clip, when given), with the reference
    as a ghost, at the control rate (MP4 or GIF)."""
    from bmimic.render import TrackingRenderer, annotate, write_video

    spec = read_policy(policy_path)
    session = policy_session(policy_path)
    chosen = None if clip is None else clip_indices(spec, [clip])
    ref = read_reference(session, spec, chosen)
    first, last = (0, spec.num_frames - 1) if chosen is None else (clip_frames(spec, chosen[0])[0],
                                                                  clip_frames(spec, chosen[0])[-1])
    mjm, _ = build_model(spec, model, run_dir, joint_dynamics)
    rollout = Rollout(mjm, spec, ref, session)
    renderer = TrackingRenderer(mjm, width, height)
    frames: list[np.ndarray] = []

    def draw(r: Rollout, terminated: bool) -> None:
        renderer.renderer.update_scene(r.d, camera=renderer.camera, scene_option=renderer.option)
        renderer.add_ghost(r.reference_qpos(r.frame))  # the renderer's ghost of the reference pose
        text = [f"sim2sim {model_label(model)}  t={r.frame / spec.fps:5.2f} s"] + (["terminated"] if terminated else [])
        frames.append(annotate(renderer.renderer.render(), text, alert=terminated))

    start = min(max(first, first + int(round(start_s * spec.fps))), last)
    try:
        run_episode(rollout, start, max(1, int(round(duration_s / spec.control_dt_s))), on_step=draw)
    finally:
        renderer.close()
    return write_video(frames, out, 1.0 / spec.control_dt_s)


# ============================================================================================ CLI
def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bmimic.sim2sim",
        description="Evaluate the exported (BeyondMimic-compatible) ONNX policy in native MuJoCo on the CPU.",
        epilog=f"Tables: RUN/{SIM2SIM_DIR}/<model>/<checkpoint>/{{{','.join((*EVAL_TABLES, GAP_FILE))}}}")
    p.add_argument("path", type=path_arg, help="a run folder (its latest checkpoints/motion_policy_<it>.onnx) or such an ONNX file")
    p.add_argument("--model", default="bmimic_g1",
                   help="bmimic_g1 (the G1 the run trained on; formerly `project`), menagerie (MuJoCo Menagerie's G1) or an MJCF path")
    p.add_argument("--episodes-per-bin", type=int, help="default: as the run's MuJoCo-Warp evaluation")
    p.add_argument("--horizon-s", type=float, help="seconds an episode must survive (default: as the run's evaluation)")
    p.add_argument("--max-mpkpe-rel-mm", type=float,
                   help="also fail episodes whose mean root-relative MPKPE exceeds this (default: as the run's evaluation)")
    p.add_argument("--workers", type=int, default=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                   else os.cpu_count() or 1, help="worker processes (default: the CPU cores available)")
    p.add_argument("--joint-dynamics", choices=("model", "metadata"), default="model",
                   help="keep the model's armature/damping/friction loss (default) or use training's")
    p.add_argument("--clip", type=lambda text: [c.strip() for c in text.split(",") if c.strip()],
                   help="a library's clip (or several, comma-separated): evaluate only its bins (with --whole-clip: "
                        "only it), read only its frames")
    p.add_argument("--video", type=path_arg, help="also render one episode to this .mp4 (or .gif)")
    p.add_argument("--video-start-s", type=float, default=0.0,
                   help="where the video episode starts in the motion (with --clip: in its first clip)")
    p.add_argument("--video-s", type=float, default=10.0, help="longest video episode in seconds")
    p.add_argument("--out", type=path_arg, help="folder for the tables (default RUN/sim2sim/<model>/<checkpoint>, "
                   f"with --whole-clip .../<checkpoint>/{SIM2SIM_WHOLE_CLIP})")
    p.add_argument("--whole-clip", type=int, metavar="R",
                   help="instead of the windows: R rollouts per clip from its first frame to its last, per condition "
                        "(nominal is deterministic here: one rollout per clip)")
    p.add_argument("--conditions", help=f"with --whole-clip: comma-separated subset of {', '.join(WHOLE_CLIP_CONDITIONS)} "
                   "(default all)")
    p.add_argument("--seed", type=int, help="with --whole-clip: seed of the robust rollouts' draws (default 0)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        require_extra("sim2sim", "python -m bmimic.sim2sim")
        if args.video is not None:
            from bmimic.render import select_gl_backend, video_path

            check_output_file("--video", video_path(args.video))  # a bad suffix or folder: refused before any work
            select_gl_backend()  # before mujoco is imported
        if args.workers < 1:
            raise Sim2SimError(f"--workers {args.workers}: need at least 1")
        if args.whole_clip is not None:
            return _whole_clip(args)
        whole_clip_only = [f for f, v in (("--conditions", args.conditions), ("--seed", args.seed)) if v is not None]
        if whole_clip_only:
            raise Sim2SimError(f"{', '.join(whole_clip_only)}: only with --whole-clip R")
        policy_path, run_dir = locate(args.path)
        result, warp, gap = evaluate(policy_path, run_dir, args.model, args.episodes_per_bin, args.horizon_s,
                                     args.workers, args.joint_dynamics, args.max_mpkpe_rel_mm, clips=args.clip)
        out = args.out or (run_dir or policy_path.parent) / SIM2SIM_DIR / model_label(args.model) / (
            result.summary["label"] + clips_suffix(args.clip))
        _write(result, gap, out.resolve())
        video = None
        if args.video is not None:
            video = render_video(policy_path, run_dir, args.model, args.joint_dynamics, args.video,
                                 args.video_start_s, args.video_s, clip=None if args.clip is None else args.clip[0])
    except user_errors() as e:
        print(f"error: {first_line(e)}", file=sys.stderr)
        return 2
    from bmimic.evaluation.report import format_report

    s = result.summary
    print(format_report(result))
    print(f"model: {s['model_description']}")
    print(f"throughput: {s['control_steps']} control steps ({s['physics_steps']} physics steps) in "
          f"{s['eval_wall_time_s']:.1f} s on {s['workers']} worker process(es): {s['control_steps_per_s']:.0f} control steps/s "
          f"({s['control_steps_per_s_per_worker']:.0f} per worker)")
    print(format_gap(result, warp, gap))
    if video is not None:
        print(f"video: {video}")
    return 0


def _whole_clip(args: argparse.Namespace) -> int:
    """`--whole-clip R`: every check first (nothing is written on a refusal), then the rollouts, the
    tables through the run record and the printed summary."""
    from bmimic.evaluation.tables import EvalResult
    from bmimic.sim2sim.whole_clip import check_rollouts, format_whole_clip, parse_conditions, run_whole_clip

    check_rollouts(args.whole_clip)
    conditions = parse_conditions(args.conditions or ",".join(WHOLE_CLIP_CONDITIONS))
    window_only = [f for f, v in (("--episodes-per-bin", args.episodes_per_bin), ("--horizon-s", args.horizon_s),
                                  ("--video", args.video)) if v is not None]
    if window_only:
        raise Sim2SimError(f"{', '.join(window_only)}: the window evaluation's; --whole-clip runs every clip whole")
    policy_path, run_dir = locate(args.path)
    result = run_whole_clip(policy_path, run_dir, args.whole_clip, conditions, args.model, args.workers,
                            args.joint_dynamics, args.max_mpkpe_rel_mm, args.seed or 0, clips=args.clip)
    out = args.out or ((run_dir or policy_path.parent) / SIM2SIM_DIR / model_label(args.model)
                       / (result.summary["label"] + clips_suffix(args.clip)) / SIM2SIM_WHOLE_CLIP)
    written = EvalResult(result.rollouts, result.bins, result.segments, result.summary)
    _write(written, None, out.resolve(), {WHOLE_CLIP_SURVIVAL: result.survival, SIM2SIM_WHOLE_CLIP_GAP: result.gap})
    print(format_whole_clip(result))
    print(f"tables: {written.out_dir}")
    return 0


def clips_suffix(clips: Sequence[str] | None) -> str:
    """How the tables' folder of a `--clip` evaluation is named after the checkpoint's: `_clip_<name>`,
    for several clips `_clips_<n>-<digest>` (never the folder of the whole motion's evaluation)."""
    import hashlib
    import re

    if clips is None:
        return ""
    if len(clips) == 1:
        return "_clip_" + (re.sub(r"[^A-Za-z0-9_.-]+", "_", clips[0]).strip("._") or "clip")
    return f"_clips_{len(clips)}-{hashlib.sha256(','.join(sorted(clips)).encode()).hexdigest()[:8]}"


def _write(result, gap, out_dir: Path, tables: dict | None = None) -> None:
    from bmimic.evaluation.tables import write_tables

    write_tables(result, out_dir, gap, tables)  # through the run record: the gap first, the summary last
