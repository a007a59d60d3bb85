"""`python -m bmimic.sim2sim RUN_DIR_OR_ONNX [options]`: the exported policy in native MuJoCo on the CPU.

    python -m bmimic.sim2sim outputs/runs/default/<stamp>                 # latest motion_policy_<it>.onnx
    python -m bmimic.sim2sim RUN --model menagerie --episodes-per-bin 8 --workers 16
    python -m bmimic.sim2sim RUN/checkpoints/motion_policy_500.onnx --model path/to/g1.xml --video dance.mp4
    python -m bmimic.sim2sim RUN --whole-clip 16                          # whole clips, nominal and robust
    python -m bmimic.sim2sim LIBRARY_RUN --clip walk1_subject1        # one clip of a library (its bins only)

A second-simulator check before a robot: the BeyondMimic-compatible ONNX (`motion_policy_<it>.onnx`,
written at every checkpoint or by `python -m bmimic.export RUN`) runs under onnxruntime in MuJoCo's C
engine (the `mujoco` bindings, not MuJoCo-Warp), and everything the control loop needs is read from
the file's metadata alone, never from bmimic's training code:

- Reference motion: the one baked into the file, read by evaluating its reference outputs at every
  time step (what BeyondMimic's deployment controller plays), not the run's motion file.
- Actuation: each joint gets a MuJoCo position-style actuator built with MjSpec from the metadata
  gains (gainprm Kp, biasprm (0, -Kp, -Kd), forcerange +-effort limit), the actuator model training
  used (`bmimic.robot.add_pd_actuator`), so the implicitfast integrator treats the Kd term implicitly
  as it did in training; a torque computed in Python once per physics step would make the damping
  explicit and change the closed loop. Control: target = default_joint_pos + action_scale * action,
  written once per control step and held for `decimation` physics steps of `physics_dt_s`.
- Observations: rebuilt in numpy from `observation_layout` (term functions and sizes), the tracked
  bodies, the anchor body and the baked reference; terminations from `terminations`; the physics
  options (integrator, solver, cone, iterations) from the `sim_*` keys.
- `--model bmimic_g1` (formerly `project`) is the G1 the run trained on (its `robot` config; the built-in G1 for a bare
  ONNX file), `menagerie` the MuJoCo Menagerie G1 (`BMIMIC_MENAGERIE_G1` or a `shared/reference`
  folder beside the checkout; mesh geoms whose files are missing are dropped, so only its primitive
  geoms collide), a path any MJCF. Joints are matched by name, a mismatch is refused. The model's own
  armature, joint damping and friction loss are kept (`--joint-dynamics model`: a model difference is
  what the check is for); `--joint-dynamics metadata` sets training's (metadata armature, none else).

The evaluation is `bmimic.eval`'s, with the same accounting (bmimic.training.evaluator):
`episodes_per_bin` episodes start at the same stratified frames of every time bin, from the reference
state, with the deterministic policy, for `horizon_s`; the reference stops at the end of its clip. An
episode that terminates fails at the frame it was judged at (with `max_mpkpe_rel_mm`, one whose mean
anchor-relative MPKPE exceeds it fails at its worst frame); failures are charged to the bin where they
happen, per visit, and per-step errors to the frame they were measured at. A physics divergence
(MuJoCo resets the state) is a termination. Settings not given are those of the MuJoCo-Warp evaluation
compared against. Episodes run in parallel, one MjData and one single-threaded onnxruntime session per
worker process. Tables (bmimic.eval's, plus `end_s`, `end_bin`, `diverged` per episode) go to
RUN/sim2sim/<model>/<checkpoint>/, with `sim2sim_gap_bins.csv`, and the gap in success rate and
anchor-relative MPKPE to the MuJoCo-Warp evaluation of the same checkpoint (RUN/eval/<checkpoint>/
from `bmimic.eval`, else the training-time evaluation in RUN/eval.parquet) is printed overall and per
bin, with a note when the two ran with different episodes per bin, horizon or MPKPE threshold.

`--whole-clip R` (`whole_clip`) runs every clip from its first frame to its last instead, nominal and
with training's perturbations (`perturb`), and writes RUN/sim2sim/<model>/<checkpoint>/whole_clip/.

Modules: `spec` reads the file's metadata and baked-in motion, `model` builds the robot model,
`rollout` is the numpy control loop (observations, terminations, errors, one episode), `workers`
spreads episodes over processes, `native_eval` runs the episodes and builds the tables, `gap` compares
them with the MuJoCo-Warp evaluation, `perturb` is the robust condition's draws, `whole_clip` the
whole-clip rollouts and their tables, `whole_clip_gap` bmimic's own whole-clip success and the gap to
it, `cli` is the command line. The simulation path (this package's imports and
everything a worker runs) uses numpy, mujoco, onnxruntime and torch-free bmimic helpers only; the
command's bookkeeping (bins, start frames, tables) reuses bmimic.evaluation's, so the two evaluations are
comparable row by row.
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

from bmimic.sim2sim.cli import main, parser, render_video
from bmimic.sim2sim.gap import GAP_FILE, SETTINGS, WarpEval, format_gap, gap_table, warp_eval
from bmimic.sim2sim.model import MENAGERIE_ENV, MODELS, build_model, find_menagerie, model_label
from bmimic.sim2sim.native_eval import MOTION_FILE, checkpoint_label, collect, evaluate, locate
from bmimic.sim2sim.rollout import ERROR_NAMES, Episode, Rollout, run_episode
from bmimic.sim2sim.spec import (
    OBS_DIMS,
    REFERENCE_OUTPUTS,
    TERMINATIONS,
    ObsTerm,
    PolicySpec,
    Sim2SimError,
    clip_frames,
    clip_indices,
    policy_session,
    read_metadata,
    read_policy,
    read_reference,
)
from bmimic.sim2sim.workers import run_episodes

__all__ = [
    "ERROR_NAMES", "GAP_FILE", "MENAGERIE_ENV", "MODELS", "MOTION_FILE", "OBS_DIMS", "REFERENCE_OUTPUTS", "SETTINGS",
    "TERMINATIONS", "Episode", "ObsTerm", "PolicySpec", "Rollout", "Sim2SimError", "WarpEval", "build_model",
    "checkpoint_label", "clip_frames", "clip_indices", "collect", "evaluate", "find_menagerie", "format_gap", "gap_table", "locate", "main",
    "model_label", "parser", "policy_session", "read_metadata", "read_policy", "read_reference", "render_video",
    "run_episode", "run_episodes", "warp_eval",
]
