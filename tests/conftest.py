"""Shared fixtures: composed configs, the repo root, the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "conf"
SHARED_MOTIONS = REPO.parent / "shared" / "motions"
"""The development copy of three LAFAN1 G1 clips (not shipped: CC BY-NC-ND); tests using it skip without it."""
if SHARED_MOTIONS.is_dir():  # data.lafan_dir defaults to $BMIMIC_LAFAN_DIR; subprocesses inherit it
    os.environ.setdefault("BMIMIC_LAFAN_DIR", str(SHARED_MOTIONS))

# Tiny sizes for end-to-end runs of the real command line on a CPU.
TINY = [
    "device=cpu", "num_envs=2", "max_iterations=2", "ppo.num_steps_per_env=8", "ppo.num_mini_batches=2",
    "motion=easy_only", "eval.horizon_s=0.2", "progress_bar=false",
]


def compose(overrides: list[str] | None = None, return_hydra_config: bool = False):
    """Compose conf/train.yaml with overrides, the way the CLI does."""
    from hydra import compose as _compose
    from hydra import initialize_config_dir

    import bmimic.config  # noqa: F401  (registers the schemas)

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return _compose("train", overrides=overrides or [], return_hydra_config=return_hydra_config)


@pytest.fixture
def cfg():
    return compose()


def free_port() -> int:
    """A TCP port on localhost that nothing listens on now (for a process group's rendezvous)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cli_env() -> dict:
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env
