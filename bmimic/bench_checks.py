"""The checks of `python -m bmimic.bench`'s command line, before any measurement: env counts, parts,
output files, device, torchrun's variables and the config each count composes to, so that a typo is
one `error:` line instead of a traceback after minutes of set-up."""

from __future__ import annotations

import argparse

from bmimic import BmimicError

PARTS = ("sim", "collect", "train", "breakdown")
"""What --only may name."""


def checked_args(args: argparse.Namespace, overrides: list[str]) -> tuple[list[int], set[str], str]:
    """(env counts, parts, device) of the command line, checked before any measurement: the counts and
    parts, the output files, the device, and the config each count composes to (bmimic.train's checks,
    the memory each count needs); BmimicError (one line) otherwise."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    import bmimic.config  # noqa: F401  (the config schemas)
    from bmimic import CONF_DIR
    from bmimic.cli.common import check_output_file, first_line
    from bmimic.config import check_overrides, placed, resolve_runtime
    from bmimic.config.checks import check_composed, validate
    from bmimic.robot import load_mjmodel
    from bmimic.runtime import resolve_device, torchrun_env
    from bmimic.task import check_networks_fit, check_num_envs_fit

    try:
        envs = [int(x) for x in args.envs.split(",")]
    except ValueError:
        envs = []
    if not envs or min(envs) < 1:
        raise BmimicError(f"--envs {args.envs!r}: expected comma-separated env counts >= 1 (e.g. 1024,4096)")
    only = set(args.only.split(","))
    if not only <= set(PARTS) or args.iters < 1:
        raise BmimicError(f"--only {args.only!r} / --iters {args.iters}: parts of {','.join(PARTS)}, iterations >= 1")
    for flag in ("--json", "--multigpu-json"):
        if getattr(args, flag[2:].replace("-", "_")) is not None:
            check_output_file(flag, getattr(args, flag[2:].replace("-", "_")))
    check_overrides(overrides)  # Hydra's refusals as one line naming the override (bmimic.config.override_error)
    torchrun_env()
    device = resolve_device(args.device)
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("train", overrides=[f"num_envs={max(envs)}", f"device={device}", *overrides],
                          return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as e:
        raise BmimicError(f"overrides after --: {first_line(e)}") from None
    check_composed(cfg, cfg.hydra.runtime.choices)
    resolve_runtime(cfg, device)
    validate(cfg, composed_checked=True)
    largest = placed(cfg)
    mjm = load_mjmodel(cfg=largest.robot)
    check_num_envs_fit(largest, mjm, device, max(envs), largest.ppo.num_steps_per_env)
    check_networks_fit(largest, mjm, device)
    return envs, only, device
