"""`python -m bmimic.train [overrides]`: train a tracking policy under a motion sampler.

    python -m bmimic.train                                   # embedded default motion, adaptive sampler
    python -m bmimic.train sampler=uniform seed=3
    python -m bmimic.train motion=lafan_dance1 sampler.gamma=0.8 num_envs=8192
    python -m bmimic.train -m +sweep=sampler_ablation        # a study from sweeps/
    python -m bmimic.train --help                            # groups and options
    python -m bmimic.train --cfg job                         # the composed config

Single runs write outputs/runs/<run_name>/<timestamp>/, multirun jobs
outputs/sweeps/<sweep_name>/<overrides>/seed=<seed>/. Returns the final evaluated failure rate
(lower is better) so Hydra's optimising sweepers can use it.
"""

from __future__ import annotations

import sys

import hydra
from hydra.errors import HydraException
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

import bmimic.sweeping.gpu_slots  # noqa: F401  (registers the bmimic.gpu_slots resolver of the launchers)
from bmimic import CONF_DIR
from bmimic.cli_common import first_line
from bmimic.config import ConfigError, check_additions, check_hydra_flags, hydra_overrides
from bmimic.extras import MissingExtraError, check_launcher
from bmimic.job import launch
from bmimic.runtime import DistributedSetupError, exit_rank, rendezvous_timeout_s, torchrun_env
from bmimic.sweeping.jobs import sweep_overrides


# An absolute config path: the console script imports this module, for which Hydra would otherwise look for
# a `bmimic.conf` Python package (conf/ is a data folder in a wheel, with no __init__.py).
@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="train")
def main(cfg: DictConfig) -> float:
    return launch(cfg)


def inspect_sweep_argv(argv: list[str]) -> list[str]:
    """Hydra runs `-m` only; with --cfg, --help or --info it refuses. For those, print the sweep's jobs
    (as YAML comments, so --cfg's output stays YAML) and return the command line that shows its first
    job the same way, without -m."""
    from hydra._internal.utils import get_args_parser

    args = get_args_parser().parse_args(argv[1:])
    if not args.multirun or not (args.cfg or args.help or args.info):
        return argv
    try:
        jobs = sweep_overrides(args.overrides)
    except Exception:  # overrides that do not compose: Hydra reports them below, in its own words
        jobs = [args.overrides]
    if args.cfg:
        print(f"# -m: {len(jobs)} jobs (python -m bmimic.launch list {' '.join(args.overrides)} lists their "
              "folders and status); the config of job 0 follows")
        for i, job in enumerate(jobs):
            print(f"#   job {i}: {' '.join(job)}")
    rest = [a for a in argv[1:] if a not in ("-m", "--multirun", *args.overrides)]
    return [argv[0], *rest, *jobs[0]]


def cli() -> None:
    """`bmimic-train` and `python -m bmimic.train`: the Hydra app with bmimic's checks around it."""
    try:
        _, world, _ = torchrun_env()  # torchrun's variables, before Hydra claims a folder with them
        rendezvous_timeout_s()
        check_launcher(sys.argv[1:])  # before Hydra composes the launcher's config, which fails unnamed
        check_additions(hydra_overrides(sys.argv[1:]))  # before OmegaConf's bare assertion can fire
    except (MissingExtraError, ConfigError, DistributedSetupError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    sys.argv = inspect_sweep_argv(sys.argv)
    try:
        check_hydra_flags(sys.argv[1:])  # (after -m with --cfg became the first job's --cfg)
        main()
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except (HydraException, OmegaConfBaseException) as e:  # --help and --info compose outside Hydra's error report
        print(f"error: {first_line(e)}", file=sys.stderr)
        sys.exit(2)
    if world > 1:
        exit_rank(0)  # a torchrun rank whose run is written: no interpreter teardown (runtime.exit_rank)


if __name__ == "__main__":
    cli()
