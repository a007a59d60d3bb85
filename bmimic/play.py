"""`python -m bmimic.play RUN_DIR_OR_CHECKPOINT [options] [key=value ...]`: render a policy tracking its motion.

    python -m bmimic.play outputs/runs/default/2026-01-01_12-00-00                 # 10 s from the start
    python -m bmimic.play RUN --start-s 12.5 --seconds 5 --out dance.mp4
    python -m bmimic.play RUN/checkpoints/model_500.pt --width 1280 --height 720 --fps 30
    MUJOCO_GL=osmesa python -m bmimic.play RUN                                     # force software GL

One evaluation world (no randomisation, no noise, deterministic policy) starts exactly on the
reference at --start-s; the robot is drawn from the simulation and the reference pose at the same
frame as a translucent ghost, through the robot's `tracking` camera. When the robot falls (a
termination) it is put back on the reference at the current frame and the video says so; at the end
of the clip the rollout starts again at --start-s. The run's config is rebuilt as in
`python -m bmimic.eval` (same overrides). Default output: RUN_DIR/videos/<checkpoint>_t<start>s.mp4,
or .gif when imageio/imageio-ffmpeg are not installed. Exit status 2 with a one-line `error: ...`
on bad input or when no OpenGL backend is available.
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import logging
import math
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from bmimic.cli.common import add_trust_flag, first_line, path_arg, user_errors
from bmimic.runs.folder import VIDEOS_DIR

log = logging.getLogger("bmimic.play")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bmimic.play",
                                description="Render a trained policy tracking its reference motion (ghost).")
    p.add_argument("path", type=path_arg, help="a run folder (uses checkpoints/latest.pt) or a checkpoint file in one")
    p.add_argument("overrides", nargs="*", help="dotted config overrides key=value (as in bmimic.eval)")
    p.add_argument("--seconds", type=float, default=10.0, help="length of the video in seconds (default 10)")
    p.add_argument("--start-s", type=float, default=0.0, help="motion time to start at, in seconds (default 0)")
    p.add_argument("--out", type=path_arg, help="video file, .mp4 or .gif (default RUN_DIR/videos/...)")
    p.add_argument("--width", type=int, default=640, help="image width in pixels (default 640)")
    p.add_argument("--height", type=int, default=480, help="image height in pixels (default 480)")
    p.add_argument("--fps", type=float, default=50.0, help="video frame rate (default 50 = the control rate)")
    p.add_argument("--device", help="cpu, cuda, cuda:N or auto (default: the run's device setting)")
    p.add_argument("--msaa", type=int, help="multisample anti-aliasing samples (default 4; 0 on software GL)")
    p.add_argument("--no-ghost", action="store_true", help="do not draw the reference ghost")
    p.add_argument("--no-text", action="store_true", help="do not print time, segment and falls on the frames")
    add_trust_flag(p)
    return p


def frame_steps(seconds: float, fps: float, step_dt: float) -> list[int]:
    """Control steps elapsed at each video frame: frame k shows the state at time k / fps."""
    n = max(1, int(round(seconds * fps)))
    return [int(round(k / fps / step_dt)) for k in range(n)]


def reference_qpos(env, world: int = 0) -> np.ndarray:
    """qpos of the reference at `world`'s current frame (free joint then hinges, as the model's qpos)."""
    return env.reference.qpos(env.time_steps[world]).double().cpu().numpy()


def rollout_frames(env, policy, renderer, start_frame: int, steps_at_frame: Sequence[int], ghost: bool = True,
                   text: bool = True) -> tuple[list[np.ndarray], list[float]]:
    """Run world 0 from `start_frame` and render one image per entry of `steps_at_frame`.

    Returns the images and the times (s since the start) at which the robot fell and was reset.
    """
    import torch

    from bmimic.evaluation.tables import segment_at
    from bmimic.render import annotate

    first = torch.tensor([start_frame], device=env.device)
    motion = env.reference.motion
    images, falls = [], []
    step = 0
    with torch.inference_mode():  # the whole rollout: env tensors rebound inside stay inference tensors
        env.reset_to_frames(first)
        obs = env.get_observations()
        for target in steps_at_frame:
            while step < target:
                obs, _, _, extras = env.step(policy(obs))
                step += 1
                if bool(extras["terminated"][0]):
                    falls.append(step * env.step_dt)
                    env.reset_to_frames(env.time_steps.clone())  # back on the reference, same frame
                elif bool(env.reached_clip_end[0]):
                    env.reset_to_frames(first)
                obs = env.get_observations()
            image = renderer.render(env.sim.data, reference_qpos(env) if ghost else None)
            if text:
                frame = int(env.time_steps[0])
                segment = segment_at(motion.segments, np.array([frame / motion.fps]))[0][0]
                recent = bool(falls) and step * env.step_dt - falls[-1] < 0.5
                lines = [f"t {step * env.step_dt:5.2f} s   motion {frame / motion.fps:6.2f} s  {segment}",
                         f"falls {len(falls)}" + ("  (reset to reference)" if recent else "")]
                image = annotate(image, lines, alert=recent)
            images.append(image)
    return images, falls


def check_video_fits(seconds: float, fps: float, width: int, height: int) -> None:
    """Refuse a video whose frames, all held in memory until it is written, would not fit (or whose
    length or rate is not a positive number) before any rollout: `--seconds 1e9` must not run for days."""
    from bmimic.render import RenderError
    from bmimic.task import free_memory_bytes

    for flag, value in (("--seconds", seconds), ("--fps", fps), ("--width", width), ("--height", height)):
        if not (math.isfinite(value) and value > 0):
            raise RenderError(f"{flag} must be > 0 and finite, got {value}")
    frames = seconds * fps
    need = max(frames, 1.0) * width * height * 3
    free = free_memory_bytes("cpu")
    if free is not None and need > free / 2:
        raise RenderError(f"--seconds {seconds:g} x --fps {fps:g} = {frames:.3g} frames of --width {width} x --height "
                          f"{height} need about {need / 2**30:.3g} GiB held in memory, more than half of the "
                          f"{free / 2**30:.1f} GiB free; make the video shorter, slower or smaller")


def play(args: argparse.Namespace) -> Path:
    """Build the run's single-world eval environment and policy, render, write the video."""
    from bmimic.cli.common import check_output_file
    from bmimic.evaluation.saved_run import checkpoint_label, load_run, load_run_checkpoint
    from bmimic.render import RenderError, TrackingRenderer, video_path, write_video
    from bmimic.task import build_evaluator
    from bmimic.training.policy import build_policy

    check_video_fits(args.seconds, args.fps, args.width, args.height)
    if args.out is not None:  # before minutes of rendering: a file in an existing folder
        check_output_file("--out", video_path(Path(args.out)))
    # eval.max_envs=1: build_evaluator then makes exactly one world.
    overrides = [*args.overrides, "eval.max_envs=1", *([f"device={args.device}"] if args.device else [])]
    run = load_run(args.path, overrides, trust=args.trust_checkpoint)
    task = run.task
    state = load_run_checkpoint(run)
    motion = task.motion
    if not 0 <= args.start_s < motion.duration_s:
        raise RenderError(f"--start-s {args.start_s}: must be in [0, {motion.duration_s:g}) s, the motion's length")
    label = checkpoint_label(run.checkpoint, state)
    out = args.out if args.out is not None else run.run_dir / VIDEOS_DIR / f"{label}_t{args.start_s:g}s.mp4"
    out = video_path(Path(out))  # fail on a bad suffix before the rollout, not after

    env = build_evaluator(task).env
    policy = build_policy(state, env, task.cfg.ppo, task.device, run.checkpoint)
    renderer = TrackingRenderer(env.sim.mjm, args.width, args.height, msaa=args.msaa)
    try:
        steps = frame_steps(args.seconds, args.fps, env.step_dt)
        start_frame = min(int(round(args.start_s * motion.fps)), motion.num_frames - 1)
        log.info("rendering %d frames (%g s at %g fps) of %s from %.2f s", len(steps), args.seconds, args.fps,
                 run.checkpoint, args.start_s)
        images, falls = rollout_frames(env, policy, renderer, start_frame, steps, ghost=not args.no_ghost,
                                       text=not args.no_text)
    finally:
        renderer.close()
    path = write_video(images, out, args.fps)
    fell = f", fell {len(falls)} times (at {', '.join(f'{t:.2f}' for t in falls[:5])} s)" if falls else ""
    print(f"wrote {path}: {len(images)} frames, {args.width}x{args.height} at {args.fps:g} fps{fell}")
    return path


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    # The GL backend must be chosen before anything imports mujoco.
    from bmimic.render import select_gl_backend

    try:
        select_gl_backend()
    except Exception as e:  # RenderError; a probe that cannot even start is the same answer
        print(f"error: {str(e).splitlines()[0] if str(e) else type(e).__name__}", file=sys.stderr)
        return 2

    from bmimic.cli.console import quiet_warp

    quiet_warp()
    try:
        play(args)
    except user_errors() as e:
        print(f"error: {first_line(e)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
