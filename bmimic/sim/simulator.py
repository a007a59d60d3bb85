"""Batched MuJoCo-Warp simulation with zero-copy torch views.

One world per environment (`nworld = num_envs`). A control step is `decimation` physics steps
followed by a kinematics pass (so body poses read after the step belong to the new qpos); on a GPU the
whole control step is one captured CUDA graph, on a CPU it runs eagerly. After writing the state
of some worlds (a reset, a teleport at the end of the motion), `forward_kinematics()` recomputes
body poses and velocities for every world, so poses read in the same step are consistent.

All torch views alias Warp memory: write them in place (`sim.qpos[ids] = x`), never rebind them,
because a captured graph holds the original pointers.
"""

from __future__ import annotations

import gc
import logging

import mujoco
import mujoco_warp as mjw
import torch
import warp as wp

from bmimic import BmimicError
from bmimic.sim.config import SimConfig

log = logging.getLogger(__name__)

_INTEGRATORS = {
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
    "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
}
_SOLVERS = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG}
# Overflow bits: buffers that lose contacts/constraints (must be reported) vs solver iteration caps.
_SOLVER_LIMIT = int(mjw.OverflowType.ITERATIONS) | int(mjw.OverflowType.LS_ITERATIONS)
_BUFFER_OVERFLOW = int(mjw.OverflowType.ALL) & ~_SOLVER_LIMIT
_CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}


def apply_sim_options(mjm: mujoco.MjModel, cfg: SimConfig) -> None:
    """Write the sim config into the host model's options (before it is put on the device)."""
    for key, table, value in (
        ("sim.integrator", _INTEGRATORS, cfg.integrator),
        ("sim.solver", _SOLVERS, cfg.solver),
        ("sim.cone", _CONES, cfg.cone),
    ):
        if value not in table:
            raise BmimicError(f"{key}: unknown value {value!r}; choose one of {sorted(table)}")
    mjm.opt.timestep = cfg.timestep_s
    mjm.opt.integrator = _INTEGRATORS[cfg.integrator]
    mjm.opt.solver = _SOLVERS[cfg.solver]
    mjm.opt.cone = _CONES[cfg.cone]
    mjm.opt.iterations = cfg.iterations
    mjm.opt.ls_iterations = cfg.ls_iterations


def warp_device(device: str) -> str:
    return "cpu" if device == "cpu" else f"cuda:{torch.device(device).index or 0}"


class Simulator:
    """`num_worlds` copies of one MuJoCo model stepped in lockstep on `device`."""

    def __init__(
        self,
        mjm: mujoco.MjModel,
        cfg: SimConfig,
        num_worlds: int,
        device: str,
        randomized_fields: tuple[str, ...] = (),
    ) -> None:
        apply_sim_options(mjm, cfg)
        self.mjm = mjm
        self.cfg = cfg
        self.num_worlds = num_worlds
        self.device = torch.device(device)
        self.wp_device = wp.get_device(warp_device(device))
        self.decimation = cfg.decimation
        self.physics_dt = cfg.timestep_s
        self.control_dt = cfg.timestep_s * cfg.decimation
        self.max_abs_qvel = float(cfg.max_abs_qvel)
        self.max_root_distance_m = float(cfg.max_root_distance_m)
        with wp.ScopedDevice(self.wp_device):
            batch = {name: num_worlds for name in randomized_fields}
            self.model = mjw.put_model(mjm, batch_sizes=batch or None)
            # Print warnings only for lost contacts/constraints; solver caps are counted, not printed.
            self.model.opt.warn_overflow = _BUFFER_OVERFLOW
            self.data = mjw.make_data(mjm, nworld=num_worlds, nconmax=cfg.nconmax, njmax=cfg.njmax)
        self._bind_views()
        self.qpos0 = torch.as_tensor(mjm.qpos0, dtype=torch.float32, device=self.device)
        self.qpos[:] = self.qpos0
        self.forward()
        self._step_graph = None
        self._kin_graph = None
        self.use_graph = cfg.use_cuda_graph and self.wp_device.is_cuda and wp.is_mempool_enabled(self.wp_device)
        if self.wp_device.is_cuda:
            # Torch and Warp share one stream: every torch op and every (graph) launch is ordered.
            torch.cuda.set_stream(wp.stream_to_torch(self.wp_device.stream))

    # ----------------------------------------------------------------------------------------- views
    def _bind_views(self) -> None:
        d, m = self.data, self.model
        t = wp.to_torch
        self.qpos = t(d.qpos)  # [N, nq]: free joint (pos 3, quat wxyz 4) then hinges
        self.qvel = t(d.qvel)  # [N, nv]: free joint (lin world 3, ang body-frame 3) then hinges
        self.ctrl = t(d.ctrl)  # [N, nu]
        self.qacc_warmstart = t(d.qacc_warmstart)  # [N, nv] the constraint solver's starting guess
        self.xpos = t(d.xpos)  # [N, nbody, 3] world body origins
        self.xquat = t(d.xquat)  # [N, nbody, 4] wxyz
        self.cvel = t(d.cvel)  # [N, nbody, 6] (ang, lin) about subtree_com of the body's root
        self.subtree_com = t(d.subtree_com)  # [N, nbody, 3]
        self.overflow = t(d.overflow)  # [N] bit flags per world
        self.nacon = t(d.nacon)  # [1]
        self.contact_geom = t(d.contact.geom)  # [naconmax, 2]
        self.contact_worldid = t(d.contact.worldid)  # [naconmax]
        self.geom_friction = t(m.geom_friction)  # [1 or N, ngeom, 3]
        self.body_ipos = t(m.body_ipos)  # [1 or N, nbody, 3]

    def restore_model_fields(self, fields: tuple[str, ...]) -> None:
        """Write the host model's values of `fields` (per-world model arrays, e.g. an event's
        `model_fields`) back into every world, in place: what startup events drew is undone."""
        for name in fields:
            view = wp.to_torch(getattr(self.model, name))
            view.copy_(torch.as_tensor(getattr(self.mjm, name), dtype=view.dtype, device=view.device).expand_as(view))

    # ----------------------------------------------------------------------------------------- stepping
    def _physics(self) -> None:
        for _ in range(self.decimation):
            mjw.step(self.model, self.data)
        self._kinematics()

    def _kinematics(self) -> None:
        mjw.kinematics(self.model, self.data)
        mjw.com_pos(self.model, self.data)
        mjw.com_vel(self.model, self.data)

    def _capture(self, fn):
        # GC suspended: a collected Warp graph destructor must not be recorded into the new graph.
        gc_was_enabled = gc.isenabled()
        gc.disable()
        try:
            torch.cuda.synchronize(self.device)
            with wp.ScopedDevice(self.wp_device):
                with wp.ScopedCapture() as cap:
                    fn()
            return cap.graph
        finally:
            if gc_was_enabled:
                gc.enable()

    def capture(self) -> None:
        """(Re)capture the graphs; call after every change of array identity (none after start-up)."""
        if not self.use_graph:
            return
        self._step_graph = self._capture(self._physics)
        self._kin_graph = self._capture(self._kinematics)
        log.info("captured CUDA graphs for the control step and kinematics (%d worlds)", self.num_worlds)

    def step(self) -> None:
        """One control step: `decimation` physics steps, then kinematics of the new state."""
        if self._step_graph is not None:
            wp.capture_launch(self._step_graph)
        else:
            with wp.ScopedDevice(self.wp_device):
                self._physics()

    def forward_kinematics(self) -> None:
        """Recompute body poses and velocities of every world from qpos/qvel (after state writes)."""
        if self._kin_graph is not None:
            wp.capture_launch(self._kin_graph)
        else:
            with wp.ScopedDevice(self.wp_device):
                self._kinematics()

    def forward(self) -> None:
        """Full mj_forward of every world (start-up only; not on the per-step path)."""
        with wp.ScopedDevice(self.wp_device):
            mjw.forward(self.model, self.data)

    # ----------------------------------------------------------------------------------------- health
    def nonfinite_worlds(self) -> torch.Tensor:
        """Bool[N]: worlds whose state is no longer finite (reset them; never let one kill the run)."""
        return ~(torch.isfinite(self.qpos).all(dim=1) & torch.isfinite(self.qvel).all(dim=1))

    def out_of_bounds_worlds(self) -> torch.Tensor:
        """Bool[N]: finite worlds beyond physical bounds (|qvel| > sim.max_abs_qvel, or the root farther
        than sim.max_root_distance_m from the origin): numerically blown up, reset them too."""
        fast = self.qvel.abs().amax(dim=1) > self.max_abs_qvel
        far = self.qpos[:, 0:3].norm(dim=1) > self.max_root_distance_m
        return fast | far

    def overflowed_worlds(self) -> torch.Tensor:
        """Bool[N]: worlds whose contact or constraint buffers overflowed during the last step."""
        return (self.overflow & _BUFFER_OVERFLOW) != 0

    def clear_overflow(self) -> None:
        self.overflow.zero_()

    def reset_broken_worlds(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(nonfinite, out_of_bounds, overflowed) Bool[N] masks of this step: the first two (disjoint)
        are put back at the initial pose (`sanitize`); the overflow flags are read and cleared."""
        nonfinite = self.nonfinite_worlds()
        out_of_bounds = self.out_of_bounds_worlds() & ~nonfinite
        self.sanitize(nonfinite | out_of_bounds)
        overflowed = self.overflowed_worlds()
        self.clear_overflow()
        return nonfinite, out_of_bounds, overflowed

    def sanitize(self, worlds: torch.Tensor) -> None:
        """Put non-finite or blown-up worlds back at the model's initial pose so they cannot poison the
        contact pool."""
        self.qpos[:] = torch.where(worlds[:, None], self.qpos0, self.qpos)
        self.qvel[:] = torch.where(worlds[:, None], torch.zeros_like(self.qvel), self.qvel)


def physics_bytes_per_world(mjm: mujoco.MjModel, cfg: SimConfig) -> int:
    """Bytes of MuJoCo-Warp state one more world costs (measured: host data for 2 worlds minus 1).

    Measured once per process for a model's sizes and the contact budgets: the training env, the
    evaluation env and the checks before them ask for the same model (~0.4 s per measurement on a CPU)."""
    key = (_model_sizes(mjm), int(cfg.nconmax), int(cfg.njmax))
    if key not in _BYTES_PER_WORLD:
        def total(nworld: int) -> int:
            with wp.ScopedDevice("cpu"):
                return _array_bytes(mjw.make_data(mjm, nworld=nworld, nconmax=cfg.nconmax, njmax=cfg.njmax), set())

        _BYTES_PER_WORLD[key] = max(total(2) - total(1), 0)
    return _BYTES_PER_WORLD[key]


_BYTES_PER_WORLD: dict[tuple, int] = {}
"""physics_bytes_per_world's measurements, by (model sizes, nconmax, njmax)."""


def _model_sizes(mjm: mujoco.MjModel) -> tuple:
    """Every integer size of the model and of its options (nq, nv, nbody, ngeom, ..., cone, jacobian): what
    make_data's allocations follow."""
    def ints(obj) -> tuple:
        return tuple((name, value) for name in dir(obj) if not name.startswith("_")
                     and isinstance(value := getattr(obj, name), int) and not isinstance(value, bool))

    return ints(mjm), ints(mjm.opt)


def _array_bytes(obj, seen: set) -> int:
    """Bytes held by the Warp arrays of a (nested) MuJoCo-Warp dataclass."""
    out = 0
    for name in getattr(obj, "__dataclass_fields__", {}):
        value = getattr(obj, name, None)
        if isinstance(value, wp.array):
            if id(value) not in seen:
                seen.add(id(value))
                out += int(value.capacity)
        elif hasattr(value, "__dataclass_fields__") and not isinstance(value, type):
            out += _array_bytes(value, seen)
    return out


__all__ = ["Simulator", "apply_sim_options", "physics_bytes_per_world", "warp_device"]
