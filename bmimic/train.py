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

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import sys

import hydra
from hydra.errors import HydraException
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

import bmimic.sweeping.gpu_slots  # noqa: F401  (registers the bmimic.gpu_slots resolver of the launchers)
from bmimic import CONF_DIR
from bmimic.cli.common import first_line, shell_arg
from bmimic.cli.extras import MissingExtraError, check_launcher
from bmimic.config import ConfigError, check_hydra_flags, check_overrides, config_loader
from bmimic.config.sources import check_config_source


# An absolute config path: the console script imports this module, for which Hydra would otherwise look for
# a `bmimic.conf` Python package (conf/ is a data folder in a wheel, with no __init__.py).
@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="train")
def main(cfg: DictConfig) -> float:
    from bmimic.job import launch  # here, not above: --help and --cfg never import training (pandas, torch)

    return launch(cfg)


def inspect_sweep_argv(argv: list[str]) -> list[str]:
    """Hydra runs `-m` only; with --cfg, --help or --info it refuses. For those, print the sweep's jobs
    (as YAML comments, so --cfg's output stays YAML) and return the command line that shows its first
    job the same way, without -m."""
    from hydra._internal.utils import get_args_parser

    args = get_args_parser().parse_args(argv[1:])
    if not args.multirun or not (args.cfg or args.help or args.info):
        return argv
    from bmimic.sweeping.jobs import sweep_overrides

    try:
        jobs = sweep_overrides(args.overrides)
    except Exception:  # overrides that do not compose: Hydra reports them below, in its own words
        jobs = [args.overrides]
    if args.cfg:
        print(f"# -m: {len(jobs)} jobs (python -m bmimic.launch list {' '.join(map(shell_arg, args.overrides))} lists their "
              "folders and status); the config of job 0 follows")
        for i, job in enumerate(jobs):
            print(f"#   job {i}: {' '.join(map(shell_arg, job))}")
    rest = [a for a in argv[1:] if a not in ("-m", "--multirun", *args.overrides)]
    return [argv[0], *jobs[0], *rest]  # overrides first: a flag with an optional value (--info) never takes one


def help_text(argv: list[str]) -> str | None:
    """`--help`'s text (bmimic.cli.help_text) for a command line that asks for it, composed once; None for
    any other command line (and for --hydra-help or another config tree: Hydra's own). Hydra's own
    --help would compose the config again for every config group it lists (its template does not use
    them), several seconds on a small machine. ConfigError (one line) for overrides that do not compose."""
    from hydra._internal.utils import get_args_parser

    from bmimic.cli.help_text import train_help
    from bmimic.config import TrainConfig

    try:
        args = get_args_parser().parse_args(argv[1:])
    except SystemExit:
        return None
    if not args.help or args.hydra_help or args.multirun:
        return None
    with config_loader() as loader:
        cfg = check_overrides(argv[1:], loader=loader)
        return None if cfg is None else train_help(cfg, TrainConfig, loader)


def cli() -> None:
    """`bmimic-train` and `python -m bmimic.train`: the Hydra app with bmimic's checks around it."""
    from bmimic.runtime import DistributedSetupError, exit_rank, rendezvous_timeout_s, torchrun_env

    try:
        _, world, _ = torchrun_env()  # torchrun's variables, before Hydra claims a folder with them
        rendezvous_timeout_s()
        check_config_source(sys.argv[1:])  # -cp/-cn/-cd that name nothing: Hydra's block and exit 1 otherwise
        check_launcher(sys.argv[1:])  # before Hydra composes the launcher's config, which fails unnamed
        # Hydra's own report of overrides that do not compose is a 5-7 line block and exit 1, and it
        # suggests `+key=...` for a typo; bmimic names the override in one line (exit 2).
        check_overrides(sys.argv[1:])
        argv = inspect_sweep_argv(sys.argv)
        if argv != sys.argv:  # --cfg, --help or --info of a sweep: its first job's overrides, without -m
            sys.argv = argv
            check_overrides(argv[1:])
        check_hydra_flags(sys.argv[1:])  # flag combinations Hydra refuses with a traceback (after -m with --cfg
        text = help_text(sys.argv)  # became the first job's --cfg)
    except (MissingExtraError, ConfigError, DistributedSetupError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    if text is not None:
        print(text)
        return
    try:
        main()
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except (HydraException, OmegaConfBaseException) as e:  # --info composes outside Hydra's error report
        print(f"error: {first_line(e)}", file=sys.stderr)
        sys.exit(2)
    if world > 1:
        exit_rank(0)  # a torchrun rank whose run is written: no interpreter teardown (runtime.exit_rank)


if __name__ == "__main__":
    cli()
