"""The optional extras of pyproject.toml and the one line a command prints when one it needs is missing.

    pip install -e ".[sim2sim]"     # python -m bmimic.sim2sim (onnxruntime)
    pip install -e ".[video]"       # MP4 videos from play and sim2sim --video (else GIF)
    pip install -e ".[parallel]"    # hydra/launcher=joblib_gpus
    pip install -e ".[slurm]"       # hydra/launcher=slurm (submitit)
    pip install -e ".[wandb]"       # logger=wandb

Torch-free: the launcher check runs before Hydra starts.
"""

from __future__ import annotations

import importlib
from typing import Sequence

from bmimic import BmimicError

EXTRAS: dict[str, tuple[tuple[str, str], ...]] = {
    "sim2sim": (("onnxruntime", "onnxruntime"),),
    "video": (("imageio", "imageio"), ("imageio_ffmpeg", "imageio-ffmpeg")),
    "parallel": (("hydra_plugins.hydra_joblib_launcher", "hydra-joblib-launcher"),),
    "slurm": (("hydra_plugins.hydra_submitit_launcher", "hydra-submitit-launcher"),),
    "wandb": (("wandb", "wandb"),),
}
"""Each extra: its (module, pip package) pairs, as pyproject.toml's [project.optional-dependencies]."""

LAUNCHER_EXTRAS = {"joblib_gpus": "parallel", "joblib": "parallel", "slurm": "slurm", "submitit_slurm": "slurm",
                   "submitit_local": "slurm"}
"""The `hydra/launcher=<name>` options and the extra each needs."""


class MissingExtraError(BmimicError):
    """A command needs an optional extra that is not installed (or, a launcher, the system it drives)."""


def _importable(module: str) -> bool:
    """`module` imports (an installed package whose import fails, e.g. a missing shared library,
    counts as missing: the command would fail on it the same way)."""
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def missing_packages(extra: str) -> list[str]:
    """The pip packages of `extra` that cannot be imported."""
    return [package for module, package in EXTRAS[extra] if not _importable(module)]


def install_command(extra: str) -> str:
    """How to install `extra`: into the checkout's editable install (the README's set-up) or a wheel."""
    return f'pip install -e ".[{extra}]" (a wheel: pip install "bmimic[{extra}]")'


def require_extra(extra: str, what: str) -> None:
    """Raise MissingExtraError, one line naming the extra and how to install it, when `what` (the
    option or command that needs it) cannot run for a missing package."""
    missing = missing_packages(extra)
    if missing:
        raise MissingExtraError(f"{what} needs the {extra} extra ({', '.join(missing)} not installed or not "
                                f"importable): "
                                f"{install_command(extra)}")


def check_launcher(overrides: Sequence[str]) -> None:
    """`hydra/launcher=<name>` among the command line's overrides: its extra must be installed (Hydra
    itself would fail composing the launcher's config, without naming the package), and the SLURM
    launcher needs SLURM (submitit fails with a traceback on a machine without `srun`)."""
    for arg in overrides:
        key, _, value = arg.lstrip("+~").partition("=")
        if key == "hydra/launcher" and value in LAUNCHER_EXTRAS:
            require_extra(LAUNCHER_EXTRAS[value], f"hydra/launcher={value}")
            if value in ("slurm", "submitit_slurm"):
                require_slurm(f"hydra/launcher={value}")


def require_slurm(what: str) -> None:
    """MissingExtraError (one line naming `what`) on a machine without SLURM (`srun` not on PATH)."""
    import shutil

    if shutil.which("srun") is None:
        raise MissingExtraError(f"{what}: this machine has no SLURM (srun is not on PATH); launch from a SLURM login "
                                "node, or leave out hydra/launcher=slurm to run the jobs here")


__all__ = ["EXTRAS", "LAUNCHER_EXTRAS", "MissingExtraError", "check_launcher", "install_command", "missing_packages",
           "require_extra", "require_slurm"]
