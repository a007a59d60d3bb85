"""`python -m bmimic.race [race options] [overrides]`: the time to a finished policy.

Trains one job, alone, exactly as `python -m bmimic.train` would with the same overrides (same run
folder, tables and checkpoints), and records, against wall time from launch (the process's start:
imports, Warp's kernel compile and the CUDA-graph capture included) and from the first iteration, the
iterations and env steps at the first evaluation where
  - evaluated success >= each of --success (default 0.90, 0.95, 0.98, 0.99), and
  - root-relative MPKPE <= each of --mpkpe-rel-mm (default 40 and 35 mm)
  - robust whole-clip success >= each of --whole-clip-success (default 0.90, 0.95): the fraction of
    rollouts from the clip's first frame that track it to its last frame under training's domain
    randomisation, observation noise and pushes (bmimic.training.whole_clip; --no-whole-clip: off),
held for --sustain evaluations in a row of that kind (default 2; the time is that of the first of them).
Training stops once every threshold is reached, at the first evaluation past --budget-s of wall time
from launch, or at max_iterations. One line per threshold is printed; RUN/race.json (and --json PATH,
e.g. under docs/bench/) holds them, every evaluation's times and the machine.

    python -m bmimic.race motion=lafan_dance1_full                  # env=tracking sampler=adaptive_hybrid
    python -m bmimic.race --budget-s 900 motion=lafan_dance1_full num_envs=8192
    python -m bmimic.race --json docs/bench/race.json motion=lafan_dance1_full sampler=uniform seed=1

It trains RACE_CONFIG (env=tracking sampler=adaptive_hybrid, the recommended configuration for a finished
policy: the confirmatory test of docs/results/confirm_hybrid_dance1) unless the overrides choose `env` or
`sampler`; `python -m bmimic.train`'s default stays the design (sampler=adaptive).

Evaluation runs every RACE_EVAL_EVERY iterations with RACE_EPISODES_PER_BIN episodes per bin unless
the overrides set eval.every_iters / eval.episodes_per_bin; its wall time counts in the race and is
also reported on its own (`eval_overhead`). A race measures one launch from its start: no -m, no
resume.

Under torchrun one process group is one race, on any number of ranks (GPUs):

    torchrun --standalone --nproc_per_node 4 -m bmimic.race motion=lafan_dance1_full num_envs=4096

The ranks gather their launch times and the clock starts at the earliest; rank 0 evaluates, decides
(every rank stops after the same iteration) and writes race.json, which also holds `gpus` (ranks),
`num_envs_per_gpu` (num_envs, per rank), `num_envs_total` and `rank_launch_spread_s` (latest minus
earliest launch). torchrun's own start (its agent, before it spawns the ranks) is not in the clock.

Whole clips are expensive: one robust evaluation of all of dance1_subject1 (6575 sequential steps) took
~51 s on an H200 whatever the number of rollouts, against ~0.24 s per training iteration. So the race
evaluates them (RACE_WHOLE_CLIP: 128 robust rollouts per clip) once the windows reached 95% success, then
after a window evaluation whenever all evaluations so far, the next one included (at the last one's
duration), stay within 10% of the wall time since the first iteration: beside the windows' 3-5%, about
one every 15 minutes of racing, so whole-clip times are that coarse (docs/benchmarks.md); where the windows
take more of the time, none (measured: 6.4% on an H200 at 4096 envs, and no whole-clip evaluation in 1250 s). So
the race also evaluates the final policy's whole clips once after its clock stopped (race.json's
`final_whole_clip`, not a threshold's time): every race says where its policy ended.

`--native-whole-clip W` judges the whole-clip thresholds in native MuJoCo instead, beside training: one
`bmimic.sim2sim` of the newest checkpoint's ONNX at a time on W CPU processes (bmimic.runs.race_judge; the
sim2sim extra, onnxruntime), checkpoints every 200 iterations (RACE_NATIVE), each result placed at its
checkpoint's evaluation, so the thresholds are timed at the policy and the GPU never pauses for them:

    python -m bmimic.race --native-whole-clip 12 motion=lafan_dance1_full num_envs=4096
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import math
import sys
from pathlib import Path

from bmimic import BmimicError
from bmimic.cli.common import check_output_file, first_line, path_arg
from bmimic.runs.race_record import LAUNCH_UNIX_S, WHOLE_CLIP_METRIC, Race, Threshold
from bmimic.runtime import (
    DistributedSetupError,
    exit_rank,
    gather_floats,
    init_distributed,
    process_rank,
    process_world,
    torchrun_env,
)

RACE_EVAL_EVERY = 100
"""Iterations between evaluations, the race's time resolution: ~24 s at 4096 envs on an H100 or H200.
Every 50 cost 9.5-12.8% of the race's wall time, every 100 costs 2.9-4.9% (docs/benchmarks.md)."""
RACE_EPISODES_PER_BIN = 16
"""Stratified episodes per bin: 2112 episodes on the 132-bin dance, one wave of the eval env."""
DEFAULT_SUCCESS = (0.90, 0.95, 0.98, 0.99)
DEFAULT_MPKPE_REL_MM = (40.0, 35.0)
DEFAULT_WHOLE_CLIP_SUCCESS = (0.90, 0.95)
RACE_CONFIG = {"env": "tracking", "sampler": "adaptive_hybrid"}
"""What the race trains unless the overrides choose: the recommended configuration for a finished policy. The
confirmatory test of sweeps/confirm_hybrid_dance1.yaml (10 v 10 fresh seeds, all of dance1, env=tracking, a rule
committed before it ran) found sampler=adaptive_hybrid's final failure lower than the design's (0.0578 vs 0.0669,
p = 0.00042), and its rule makes the hybrid the race's default (docs/results/confirm_hybrid_dance1/report.md).
`python -m bmimic.train` keeps the design (sampler=adaptive) as its default."""
RACE_WHOLE_CLIP = {"eval.whole_clip.conditions": "[robust]", "eval.whole_clip.rollouts": 128,
                   "eval.whole_clip.after_success": 0.95, "eval.whole_clip.max_share": 0.10,
                   "eval.whole_clip.at_end": "true"}
"""The race's whole-clip evaluation unless the overrides set it: robust, 128 rollouts (one latency-bound wave on
a GPU), from 95% window success, whenever all evaluations stay within 10% of the wall time (module docstring),
and once more for the final policy after the clock stopped (race.json's `final_whole_clip`): a race on one H200
(docs/bench/2026-11-29_h200_race_4096_whole_clip.json) spent its 1250 s without one, its windows alone taking
6.4% of the wall time, so the share rule never had room."""


RACE_NATIVE = {"ppo.save_interval": 200, "eval.whole_clip.rollouts": 128, "eval.whole_clip.after_success": 0.95}
"""With --native-whole-clip, unless the overrides set them: a checkpoint (and its ONNX export, which the judge
evaluates) every 200 iterations, a multiple of the evaluation's 100 so that each result lands on an evaluation
(the default 500 would judge the dance every ~2 minutes of an H200; a save every 100 would cost ~5% of the wall
time in exports); 128 robust rollouts per judgement, from the first window evaluation at 95% success, as
RACE_WHOLE_CLIP's. None of these turns MuJoCo-Warp's whole-clip evaluation on."""


def _floats(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected finite comma-separated numbers, got {text!r}")
    return values


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    """Race options, and the rest (Hydra overrides of the train config)."""
    p = argparse.ArgumentParser(prog="python -m bmimic.race", description=__doc__.split("\n\n")[0],
                                epilog="Every other argument is a Hydra override of the train config. "
                                       + __doc__.split("\n\n")[-1])
    p.add_argument("--budget-s", type=float, default=3600.0,
                   help="stop at the first evaluation this many seconds of wall time after launch (default 3600)")
    p.add_argument("--success", type=_floats, default=DEFAULT_SUCCESS, help="success thresholds, e.g. 0.9,0.99")
    p.add_argument("--mpkpe-rel-mm", type=_floats, default=DEFAULT_MPKPE_REL_MM,
                   help="root-relative MPKPE thresholds in mm (default 40,35)")
    p.add_argument("--whole-clip-success", type=_floats, default=DEFAULT_WHOLE_CLIP_SUCCESS,
                   help="robust whole-clip success thresholds (default 0.9,0.95; when whole clips are evaluated: below)")
    p.add_argument("--no-whole-clip", action="store_true", help="race to the window thresholds only")
    p.add_argument("--native-whole-clip", type=int, metavar="WORKERS", default=None,
                   help="judge the whole-clip thresholds in native MuJoCo on WORKERS CPU processes beside training "
                        "(bmimic.runs.race_judge; needs onnxruntime) instead of MuJoCo-Warp evaluations that pause it")
    p.add_argument("--sustain", type=int, default=2, help="evaluations in a row a threshold must hold (default 2)")
    p.add_argument("--json", type=path_arg, default=None, help="also write the result here (e.g. docs/bench/...json)")
    args, rest = p.parse_known_args(argv)
    problems = []
    if not (math.isfinite(args.budget_s) and args.budget_s > 0):
        problems.append(f"--budget-s must be a finite number of seconds > 0, got {args.budget_s}")
    if not all(0.0 < v <= 1.0 for v in args.success):
        problems.append(f"--success thresholds must lie in (0, 1], got {','.join(map(str, args.success))}")
    if not all(0.0 < v <= 1.0 for v in args.whole_clip_success):
        problems.append("--whole-clip-success thresholds must lie in (0, 1], got "
                        f"{','.join(map(str, args.whole_clip_success))}")
    if not all(v > 0 for v in args.mpkpe_rel_mm):
        problems.append("--mpkpe-rel-mm thresholds must be > 0 mm")
    if args.sustain < 1:
        problems.append(f"--sustain must be >= 1, got {args.sustain}")
    if args.native_whole_clip is not None and args.native_whole_clip < 1:
        problems.append(f"--native-whole-clip must be >= 1 worker, got {args.native_whole_clip}")
    if args.native_whole_clip is not None and args.no_whole_clip:
        problems.append("--native-whole-clip and --no-whole-clip contradict each other")
    try:
        if args.json is not None:
            check_output_file("--json", args.json)
        torchrun_env()  # malformed torchrun variables: one line before anything starts
    except BmimicError as e:
        problems.append(str(e))
    for flag in ("-m", "--multirun"):
        if flag in rest:
            problems.append("a race times one job from its launch: run seeds or arms as separate commands, not -m")
    if any(a.split("=", 1)[0].lstrip("+~") == "resume" for a in rest):
        problems.append("a race measures a run from its launch: resume is not raced")
    if problems:
        _refuse(problems[0])
        raise SystemExit(2)
    return args, rest


def _refuse(problem: str) -> None:
    """The `error:` line of a refusal (exit status 2). Under torchrun every rank refuses alike and rank 0
    alone prints; the ranks then leave together, since torchrun stops the others as soon as one exits."""
    if process_rank() == 0:
        print(f"error: {problem}", file=sys.stderr, flush=True)
    if process_world() > 1:
        import torch

        try:
            init_distributed()
        except DistributedSetupError:  # no peers came to leave with: a rank other than 0 says it itself
            if process_rank() != 0:
                print(f"error: {problem}", file=sys.stderr, flush=True)
            return
        torch.distributed.barrier()  # rank 0 has printed


def race_overrides(rest: list[str], whole_clip: bool = True, native: bool = False) -> list[str]:
    """The race's configuration (RACE_CONFIG), evaluation schedules (`whole_clip`: RACE_WHOLE_CLIP too; `native`:
    RACE_NATIVE instead, the judge's settings) and run name, each unless overridden."""
    keys = {a.split("=", 1)[0].lstrip("+") for a in rest if "=" in a}
    schedule = RACE_NATIVE if native else RACE_WHOLE_CLIP if whole_clip else {}
    defaults = {"eval.every_iters": RACE_EVAL_EVERY, "eval.episodes_per_bin": RACE_EPISODES_PER_BIN, "run_name": "race",
                **RACE_CONFIG, **schedule}
    extra = [f"{k}={v}" for k, v in defaults.items() if k not in keys]
    return [*extra, *rest]


def main(argv: list[str] | None = None) -> int:
    """The race; under torchrun (WORLD_SIZE > 1) every rank runs it and the rank ends without the
    interpreter's teardown, as bmimic.train's do (bmimic.runtime.exit_rank)."""
    if process_world() <= 1:
        return _race(argv)
    import torch

    try:
        code = _race(argv)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    if torch.distributed.is_initialized():  # a launch refused before training: training destroys it otherwise
        torch.distributed.destroy_process_group()
    exit_rank(code)
    return code  # not reached


def _race(argv: list[str] | None) -> int:
    args, rest = parse_args(sys.argv[1:] if argv is None else argv)
    native = args.native_whole_clip is not None
    from bmimic.config import ConfigError, check_hydra_flags, check_overrides
    from bmimic.config.sources import check_config_source

    try:  # before anything trains: flags Hydra refuses with a traceback, overrides that do not compose (one
        check_config_source(rest)  # line each, as bmimic.train), a config folder or name that names nothing
        check_hydra_flags(rest)
        check_overrides(race_overrides(rest, whole_clip=not args.no_whole_clip, native=native))
    except ConfigError as e:
        _refuse(str(e))
        return 2
    thresholds = ([Threshold("eval_success_rate", v) for v in args.success]
                  + [Threshold("eval_mpkpe_rel_mm", v) for v in args.mpkpe_rel_mm]
                  + ([] if args.no_whole_clip else [Threshold(WHOLE_CLIP_METRIC, v) for v in args.whole_clip_success]))
    race = Race(thresholds, args.budget_s, args.sustain)
    result: dict = {}
    if process_world() > 1:
        try:
            init_distributed()  # the process group training would join: joined now, to gather the launch times
        except DistributedSetupError as e:  # every rank its own line: its peers never came
            print(f"error: {e}", file=sys.stderr, flush=True)
            return 2
        race.join_ranks(gather_floats(LAUNCH_UNIX_S))

    import hydra
    from hydra.errors import HydraException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from bmimic import CONF_DIR
    from bmimic.job import launch
    from bmimic.runs.folder import METRICS, PROVENANCE, RACE, atomic_write_json, read_json

    # An absolute config path: the app runs from this module whether started with -m or imported.
    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="train")
    def app(cfg) -> float:
        from hydra.core.hydra_config import HydraConfig

        if native and cfg.ppo.save_interval % cfg.eval.every_iters:
            _refuse(f"--native-whole-clip: ppo.save_interval ({cfg.ppo.save_interval}) must be a multiple of "
                    f"eval.every_iters ({cfg.eval.every_iters}), so that each judged checkpoint falls on an evaluation")
            raise SystemExit(2)
        if native and process_rank() == 0:  # rank 0 decides; the judge's children run on its host's CPU cores
            from bmimic.runs.race_judge import NativeJudge

            race.judge = NativeJudge(args.native_whole_clip, int(cfg.eval.whole_clip.rollouts), int(cfg.seed),
                                     float(cfg.eval.whole_clip.after_success or 0.0))
        out = launch(cfg, stop_rule=race.on_evaluation)
        # The env group chosen (the race's default or an override): the overrides alone do not say it.
        env = HydraConfig.get().runtime.choices.get("env") if HydraConfig.initialized() else None
        result["config"] = {"overrides": rest, "env": env, "sampler": cfg.sampler.name, "motion": cfg.motion.name,
                            "env_action_rate": OmegaConf.select(cfg, "env.rewards.action_rate.weight"),
                            "num_envs": cfg.num_envs, "seed": cfg.seed, "device": cfg.device,
                            "eval": OmegaConf.to_container(cfg.eval),
                            **({"native_whole_clip_workers": args.native_whole_clip} if native else {})}
        return out

    saved = sys.argv
    sys.argv = [saved[0], *race_overrides(rest, whole_clip=not args.no_whole_clip, native=native)]
    try:
        app()
    except SystemExit as e:  # launch's one-line refusals (exit 2) end the race the same way
        if e.code not in (0, None):
            return int(e.code) if isinstance(e.code, int) else 2
    except (HydraException, OmegaConfBaseException) as e:  # --help and --info compose outside Hydra's error report
        _refuse(first_line(e))
        return 2
    finally:
        sys.argv = saved
        if race.judge is not None:  # no sim2sim child outlives a race that failed or was interrupted
            race.judge.close()
    if any(a in rest for a in ("--cfg", "-c", "--info", "-i", "--hydra-help", "--resolve")):
        return 0  # Hydra printed what was asked; nothing ran
    if process_rank() != 0:
        return 0  # rank 0 evaluated and writes the race
    if race.run_dir is None:
        print("error: the race ran no evaluation (eval.every_iters=0, or max_iterations below it)", file=sys.stderr)
        return 2
    metrics = read_json(Path(race.run_dir) / METRICS) or {}
    if race.judge is not None:  # the final policy in native MuJoCo, after the clock (what the judge had running stops)
        race.record_final_native(race.judge.judge_now(race.run_dir, int(metrics.get("iterations", -1))), metrics)
    else:
        race.record_final(metrics)
    record = race.to_json(result.get("config", {}), read_json(Path(race.run_dir) / PROVENANCE))
    atomic_write_json(Path(race.run_dir) / RACE, record)
    if args.json is not None:
        atomic_write_json(args.json, record)
    for line in race.lines():
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
