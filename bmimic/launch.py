"""`python -m bmimic.launch list [overrides]`: the dry run of a sweep.

    python -m bmimic.launch list +sweep=gamma                 # the jobs of a study, their folders and status
    python -m bmimic.launch list +sweep=gamma seed=0 sampler.gamma=0.5,0.9   # with overrides, as for train

The dry run expands a multirun exactly as `python -m bmimic.train -m <same overrides>` would
(bmimic.sweeping.jobs), so what it prints is what the sweep will do, including which jobs are
already done, and whether this machine would refuse the sweep (on a CPU: its estimated training time
over max_cpu_hours). It keeps torch and the simulator out of its imports.
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import sys
from typing import Sequence

from bmimic.cli.deferred import defer
from bmimic.sweeping.jobs import SweepListError, available_studies, check_job_runs, format_jobs, list_jobs


def main(argv: Sequence[str] | None = None) -> int:
    if argv is None:  # this process is the command: nothing else will need them (bmimic.cli.deferred)
        # The config checks import the env terms and sampler classes, whose modules import torch (and
        # mujoco) at their top, for their signatures and checks alone.
        for name in ("torch", "mujoco"):
            defer(name)
    parser = argparse.ArgumentParser(
        prog="python -m bmimic.launch",
        description="Dry run of a sweep: list the jobs `python -m bmimic.train -m OVERRIDES` would run, "
                    "their folders and status, without running anything.",
        epilog=f"studies: {', '.join(available_studies())}",
    )
    parser.add_argument("command", choices=["list"], help="list: print the jobs of the sweep")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, as for bmimic.train (e.g. +sweep=gamma)")
    args = parser.parse_args(argv)
    import yaml
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from bmimic import BmimicError
    from bmimic.cli.extras import check_launcher
    from bmimic.config import check_additions, override_error

    try:
        check_launcher(args.overrides)
        check_additions(args.overrides)
        sweep_dir, jobs = list_jobs(args.overrides)
    except yaml.YAMLError as e:  # a sweep file of the user's own that is not YAML (a tag, a bracket left open)
        print(f"error: a config or sweep file is not valid YAML: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except (SweepListError, HydraException, OmegaConfBaseException, BmimicError) as e:
        # Hydra's and OmegaConf's refusals as bmimic.train words them (bmimic.config.override_error)
        text = str(e) if isinstance(e, BmimicError) else override_error(e, args.overrides)
        msg = text.strip().splitlines()[0] if text.strip() else type(e).__name__
        if "sweep" in msg and "Could not" in msg:
            msg += f" (studies: {', '.join(available_studies())})"
        print(f"error: {msg}", file=sys.stderr)
        return 2
    print(format_jobs(sweep_dir, jobs))
    try:  # after the listing: which folders hold runs of other settings shows above
        check_job_runs(jobs)
    except SweepListError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from bmimic.config.budget import BudgetError, check_sweep
    from bmimic.runtime import guess_device

    try:  # what `train -m` would refuse on this machine before any job runs (its CPU budget), torch-free
        check_sweep(jobs, resolve=guess_device)
    except BudgetError as e:
        print(f"this machine would refuse the sweep: {e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
