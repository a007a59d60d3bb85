"""Batched MuJoCo-Warp simulation layer. The simulator (Warp, torch) is imported on first use, so that
the config schema (`SimConfig`) composes without them."""

from bmimic.sim.config import SimConfig


def __getattr__(name: str):
    if name in ("Simulator", "apply_sim_options"):
        from bmimic.sim import simulator

        return getattr(simulator, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["SimConfig", "Simulator", "apply_sim_options"]
