"""Schema of the `sim` config group: physics options and MuJoCo-Warp buffer sizes."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SimConfig:
    timestep_s: float = 0.005
    """Physics time step in seconds (BeyondMimic/mjlab: 0.005)."""
    decimation: int = 4
    """Physics steps per control step; 4 x 0.005 s gives the 50 Hz policy rate the motions are stored at."""
    integrator: str = "implicitfast"
    """MuJoCo integrator: euler | implicitfast | implicit | rk4."""
    solver: str = "newton"
    """Constraint solver: newton | cg."""
    cone: str = "pyramidal"
    """Friction cone: pyramidal | elliptic."""
    iterations: int = 10
    """Maximum solver iterations (worlds exit early once converged)."""
    ls_iterations: int = 20
    """Maximum line-search iterations of the solver."""
    nconmax: int = 48
    """Contacts per world (MuJoCo-Warp 4.0 semantics: the pool holds nworld * nconmax).
    The G1 on flat ground uses about 13 on average, 17 at the 95th percentile (mujoco_warp nightly);
    overflow is detected every control step and reported."""
    njmax: int = 256
    """Constraint rows per world (hard limit). Contacts x pyramid edges + joint limits; overflow is reported."""
    max_abs_qvel: float = 1000.0
    """A world whose generalised velocity exceeds this (m/s or rad/s; the G1's joints stay below
    ~40 rad/s) has blown up numerically: it is reset and counted, like a non-finite one."""
    max_root_distance_m: float = 1000.0
    """A world whose root is farther than this from the origin is reset and counted (float32 loses
    centimetres of body position beyond ~1 km)."""
    use_cuda_graph: bool = True
    """Replay the control step (decimation physics steps) as one captured CUDA graph on a GPU."""
    compile_env_step: bool = True
    """On a GPU with use_cuda_graph, fuse the training environment's per-step torch work (state,
    terminations, rewards, sampler update, resets, observations) with torch.compile before it is
    captured: far fewer kernels per step (+11-19% collection on an H100, docs/benchmarks.md). Costs
    ~40 s of compilation at start-up, a few seconds once torch's on-disk cache holds it. If
    compilation fails, the step is captured uncompiled and a warning says why."""
