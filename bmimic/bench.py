"""`python -m bmimic.bench`: throughput of physics, collection and full PPO iterations.

    python -m bmimic.bench --envs 1024,4096,8192,16384                  # on the GPU
    python -m bmimic.bench --envs 8 --iters 3 --device cpu              # smoke test
    python -m bmimic.bench --envs 4096 --only sim -- motion=lafan_dance1   # Hydra overrides after --

For each env count, in one process on one device:
  (a) physics alone: the captured control-step graph (decimation physics steps + kinematics);
  (b) collection: environment steps with policy inference, as in a PPO rollout;
  (c) full PPO iterations: collection plus the update;
plus device memory, the ratios b/a and c/a, and a breakdown of one environment step (physics,
state, observations, rewards, terminations, sampler, resets, policy) and the PPO update per
iteration, each timed in isolation with device synchronisation. Prints a table and writes JSON (--json).

Several GPUs, one run: under torchrun, `--multigpu-json PATH` times (c) on every rank (num_envs per
rank, the slowest rank's iteration time) and merges one row per env count into PATH, a list of
{gpus, num_envs_per_gpu, env_steps_per_s, scaling}; run it once per GPU count:

    for g in 1 2 4; do torchrun --standalone --nproc_per_node $g -m bmimic.bench --envs 4096 --iters 20 \
        --multigpu-json docs/bench/$(date +%F)_h200_multigpu.json; done
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bmimic.cli.deferred import import_on_first_use

if TYPE_CHECKING:
    import torch
else:  # `--help` and the argument checks need no torch (2.8 s of a 2-core machine's start-up)
    torch = import_on_first_use("torch", globals())

from bmimic import BmimicError
from bmimic.cli.common import path_arg
from bmimic.runs import safe_read


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _timeit(fn, n: int, device: str, warmup: int = 3) -> float:
    """Seconds per call."""
    for _ in range(warmup):
        fn()
    _sync(device)
    t = time.perf_counter()
    for _ in range(n):
        fn()
    _sync(device)
    return (time.perf_counter() - t) / n


def _mem_used(device: str) -> float | None:
    if not device.startswith("cuda"):
        return None
    free, total = torch.cuda.mem_get_info()
    return (total - free) / 2**30


def _slowest_rank(seconds: float, device: str) -> float:
    """Under torchrun, the largest of the ranks' times (a run goes at its slowest rank's pace)."""
    dist = torch.distributed
    if not (dist.is_available() and dist.is_initialized()):
        return seconds
    t = torch.tensor(seconds, dtype=torch.float64, device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return float(t)


def bench_one(num_envs: int, device: str, iters: int, only: set[str], overrides: list[str],
              rank: int = 0) -> dict:
    from hydra import compose, initialize_config_dir

    import bmimic.config  # noqa: F401
    from bmimic import CONF_DIR
    from bmimic.config import placed, resolve_runtime
    from bmimic.config.checks import validate
    from bmimic.runtime import seed_everything
    from bmimic.task import build_trainer, build_training

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        composed = compose("train", overrides=[f"num_envs={num_envs}", f"device={device}", *overrides])
    resolve_runtime(composed, device)
    validate(composed)  # bench_checks checked these overrides at the largest size; this size's values too
    cfg = placed(composed)
    seed_everything(cfg.seed + rank)  # distinct worlds per rank, as train.py does
    mem0 = _mem_used(device)
    t0 = time.perf_counter()
    training = build_training(cfg, device)
    env, layout, motion = training.env, training.task.layout, training.task.motion
    setup_s = time.perf_counter() - t0
    # What was timed, beside how fast: the sampler and motion (the environment's commit is environment_info's).
    out: dict = {"sampler": str(cfg.sampler.name), "motion": str(cfg.motion.name),
                 "num_envs": num_envs, "num_bins": layout.num_bins, "motion_s": motion.duration_s,
                 "setup_s": setup_s, "cuda_graph": bool(env.sim.use_graph),
                 "compile_env_step": bool(cfg.sim.compile_env_step)}
    n = num_envs
    sim_steps = max(iters * 10, 20)

    if "sim" in only:
        out["physics_steps_per_s"] = n / _timeit(env.sim.step, sim_steps, device)

    # The trainer builds the algorithm as training does; it never writes (no learn, no checkpoint).
    trainer = build_trainer(training, None, tempfile.mkdtemp(prefix="bmimic-bench-"))
    alg = trainer.alg
    if trainer.runner.is_distributed:
        alg.broadcast_parameters()  # one policy on every rank, as Trainer.learn starts
    obs = env.get_observations()
    state = {"obs": obs}

    def collect_step():
        with torch.inference_mode():
            actions = alg.act(state["obs"])
            o, r, d, e = env.step(actions)
            alg.process_env_step(o, r, d, e)
            state["obs"] = o

    steps = cfg.ppo.num_steps_per_env

    def rollout():
        for _ in range(steps):
            collect_step()
        with torch.inference_mode():
            env.end_rollout()  # the sampler update of update_every=iteration, as in Trainer.learn

    def rollout_and_returns():
        rollout()
        with torch.inference_mode():
            alg.compute_returns(state["obs"])

    if "collect" in only or "train" in only:
        def rollout_only():
            rollout()
            alg.storage.clear()

        out["collect_steps_per_s"] = n * steps / _timeit(rollout_only, iters, device, warmup=1)

    if "train" in only:
        def iteration():
            rollout_and_returns()
            alg.update()

        sec = _timeit(iteration, iters, device, warmup=2)  # the second update captures its graphs
        sec = _slowest_rank(sec, device)
        out["train_steps_per_s"] = n * steps / sec
        out["iteration_s"] = sec

        # The update alone (it needs a filled rollout storage, so each timed update follows an
        # untimed rollout); the iteration's other part is the rollout and returns.
        update_s = []
        for _ in range(max(iters, 2)):
            rollout_and_returns()
            _sync(device)
            t0 = time.perf_counter()
            alg.update()
            _sync(device)
            update_s.append(time.perf_counter() - t0)
        out["ppo_update_s"] = sorted(update_s)[len(update_s) // 2]

    if "breakdown" in only:
        out["breakdown_ms"] = breakdown(env, alg, device, sim_steps)
    if device.startswith("cuda"):
        out["mem_used_gib"] = (_mem_used(device) or 0.0) - (mem0 or 0.0)
        out["torch_max_allocated_gib"] = torch.cuda.max_memory_allocated() / 2**30
    if "physics_steps_per_s" in out:
        for k in ("collect_steps_per_s", "train_steps_per_s"):
            if k in out:
                out[k.replace("_steps_per_s", "_over_physics")] = out[k] / out["physics_steps_per_s"]
    # Graphs that hold NCCL calls must go before the process group does (pytorch/pytorch#115388).
    alg.release_graphs()
    env.close()
    return out


def breakdown(env, alg, device: str, n: int) -> dict[str, float]:
    """Milliseconds per environment step spent in each part, each timed alone through its public
    interface (the state, the observation, reward and termination managers, the sampler and its
    feedback). `resets` starts a new segment in every world (`SampledEpisodes.start`: sampling, reference
    state, kinematics), the most a step's masked resets can cost."""
    ones = torch.ones(env.num_envs, dtype=torch.bool, device=env.device)
    zeros = torch.zeros_like(ones)
    from bmimic.envs.state import compute_state

    acc = env.feedback
    length = env.episode_length_buf
    obs = env.get_observations()

    parts = {
        "physics": env.sim.step,
        "kinematics_after_writes": env.sim.forward_kinematics,
        "state": lambda: compute_state(env.sim, env.reference, env.bodies, env.time_steps),
        "observations": lambda: env.observations.compute(env),
        "rewards": lambda: env.rewards.compute(env),
        "terminations": lambda: env.terminations.compute(env),
        # Counting every env as finished, plus one sampler update (each step for update_every=step,
        # once per iteration for update_every=iteration).
        "sampler_update": lambda: acc.sampler.update_counts(
            *acc.count(ones, zeros, env.time_steps, env.segment_start, zeros, zeros, length)),
        "resets": lambda: env.episodes.start(env, zeros, zeros),
        "policy": lambda: alg.act(obs),
    }
    out = {}
    with torch.inference_mode():
        for name, fn in parts.items():
            out[name] = 1000.0 * _timeit(fn, n, device)
        out["env_step_total"] = 1000.0 * _timeit(lambda: env.step(torch.zeros(env.num_envs, env.num_actions, device=env.device)), n, device)
    return out


def environment_info(device: str) -> dict:
    """Where the numbers came from: code commit (runtime.source_commit), Python, date, device, versions."""
    from bmimic.runtime import source_commit

    commit, dirty = source_commit()
    info = {"python": platform.python_version(), "date": time.strftime("%Y-%m-%d"), "device": device,
            "git_commit": commit, "git_dirty": dirty}
    for lib in ("torch", "warp-lang", "mujoco", "mujoco-warp", "rsl-rl-lib"):
        try:
            info[lib] = version(lib)
        except Exception:
            info[lib] = None
    if device.startswith("cuda"):
        info["gpu"] = torch.cuda.get_device_name()
    else:
        info["cpu"] = platform.processor() or platform.machine()
    return info


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    overrides: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, overrides = argv[:i], argv[i + 1 :]
    p = argparse.ArgumentParser(prog="python -m bmimic.bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", default="1024,4096,8192,16384", help="comma-separated env counts")
    p.add_argument("--iters", type=int, default=5, help="PPO iterations timed per measurement")
    p.add_argument("--device", default="auto")
    p.add_argument("--only", default="sim,collect,train,breakdown", help="subset of sim,collect,train,breakdown")
    p.add_argument("--json", type=path_arg, default=None, help="write the results here")
    p.add_argument("--multigpu-json", type=path_arg, default=None, metavar="PATH",
                   help="under torchrun: time full PPO iterations on every rank and merge the total env steps/s "
                        "into PATH (one row per GPU count and env count, scaling against the 1-GPU row)")
    args = p.parse_args(argv)
    from bmimic.bench_checks import checked_args
    from bmimic.cli.common import first_line, user_errors

    try:
        if args.multigpu_json:  # a malformed file is one line, before the checks that start Warp
            read_multigpu_rows(args.multigpu_json)
        envs, only, device = checked_args(args, overrides)
        if args.multigpu_json:
            return multigpu(args, overrides, envs)
    except user_errors() as e:
        print(f"error: {first_line(e)}", file=sys.stderr)
        return 2
    results: dict[str, Any] = {"environment": environment_info(device), "overrides": overrides, "runs": []}
    if results["environment"]["git_commit"] is None:  # a copy of the tree without .git (a lent machine)
        print("warning: no git commit found for this code; set BMIMIC_SOURCE_COMMIT=<commit> so that the results "
              "record which code they measured", file=sys.stderr)
    for n in envs:
        r = bench_one(n, device, args.iters, only, overrides)
        results["runs"].append(r)
        print(json.dumps(r), flush=True)
    print(format_table(results["runs"]))
    if args.json:
        from bmimic.runs.folder import atomic_write_json

        atomic_write_json(args.json, results)
    return 0


MULTIGPU_KEYS = ("gpus", "num_envs_per_gpu", "env_steps_per_s", "scaling")


def read_multigpu_rows(path: str | os.PathLike) -> list[dict]:
    """The rows of a `--multigpu-json` file ([] when it does not exist yet); one line naming the
    file and the problem when it is not such a list."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        rows = safe_read.read_json(path, finite=True)  # Infinity would pass `> 0`, then be written back as null
    except (OSError, ValueError) as e:
        raise BmimicError(f"{path}: not readable as JSON ({e})") from None
    if not isinstance(rows, list):
        raise BmimicError(f"{path}: expected a list of {{{', '.join(MULTIGPU_KEYS)}}} objects")
    for i, r in enumerate(rows):
        ok = (isinstance(r, dict) and set(r) == set(MULTIGPU_KEYS)
              and all(isinstance(r[k], int) and r[k] >= 1 for k in ("gpus", "num_envs_per_gpu"))
              and isinstance(r["env_steps_per_s"], (int, float)) and r["env_steps_per_s"] > 0)
        if not ok:
            raise BmimicError(f"{path}: row {i} is not an object with keys {', '.join(MULTIGPU_KEYS)} "
                              "(gpus and num_envs_per_gpu positive integers, env_steps_per_s positive)")
    return rows


def merge_multigpu_rows(path: str | os.PathLike, new_rows: list[dict]) -> list[dict]:
    """Merge one measurement's rows into `path` (atomically) and return the file's rows: a row with
    the same gpus and num_envs_per_gpu is replaced, and every row's scaling is its env steps/s over
    the 1-GPU row's with the same num_envs_per_gpu (null until that row exists)."""
    from bmimic.runs.folder import atomic_write_json

    rows = {(r["gpus"], r["num_envs_per_gpu"]): r for r in read_multigpu_rows(path)}
    for r in new_rows:
        rows[(int(r["gpus"]), int(r["num_envs_per_gpu"]))] = r
    bad = [r for r in rows.values() if not (math.isfinite(float(r["env_steps_per_s"])) and r["env_steps_per_s"] > 0)]
    if bad:  # a measurement that is not a positive finite rate is never written (JSON would say null)
        raise BmimicError(f"{path}: not written: env_steps_per_s {bad[0]['env_steps_per_s']} measured with "
                          f"{bad[0]['gpus']} GPU(s) x {bad[0]['num_envs_per_gpu']} envs is not a positive finite rate")
    one_gpu = {n: r["env_steps_per_s"] for (g, n), r in rows.items() if g == 1}
    out = []
    for g, n in sorted(rows, key=lambda k: (k[1], k[0])):
        eps = float(rows[(g, n)]["env_steps_per_s"])
        out.append({"gpus": g, "num_envs_per_gpu": n, "env_steps_per_s": eps,
                    "scaling": eps / one_gpu[n] if n in one_gpu else None})
    atomic_write_json(path, out)
    return out


def multigpu(args: argparse.Namespace, overrides: list[str], envs: list[int]) -> int:
    """`--multigpu-json`: full PPO iterations on every rank of this torchrun, rank 0 merges the rows."""
    from bmimic.runtime import exit_rank, init_distributed, resolve_device, torchrun_env, use_cpu_threads

    path = Path(args.multigpu_json)
    read_multigpu_rows(path)  # a malformed file stops the run here, before any measurement
    rank, world = init_distributed()
    device = resolve_device(args.device)
    use_cpu_threads(device)  # as a training run on this device
    if world > 1 and torch.distributed.get_backend() == "nccl":
        device = f"cuda:{torchrun_env()[2]}"
    rows = []
    try:
        for n in envs:
            r = bench_one(n, device, args.iters, {"train"}, overrides, rank=rank)
            # Every rank steps its own n envs; the iteration time is the slowest rank's.
            rows.append({"gpus": world, "num_envs_per_gpu": n, "env_steps_per_s": world * r["train_steps_per_s"]})
    finally:
        if world > 1:
            # Every rank leaves together: a rank tearing down its group while another is still in
            # its last collective can abort at exit (seen once in ten CPU runs without it).
            torch.distributed.barrier()
            torch.distributed.destroy_process_group()
    if rank == 0:
        table = merge_multigpu_rows(path, rows)
        print("gpus | envs per GPU | env steps/s | scaling")
        for r in table:
            scaling = "-" if r["scaling"] is None else f"{r['scaling']:.2f}x"
            print(f"{r['gpus']} | {r['num_envs_per_gpu']} | {r['env_steps_per_s']:,.0f} | {scaling}")
        print(f"-> {path}")
    if world > 1:
        exit_rank(0)
    return 0


def format_table(runs: list[dict]) -> str:
    cols = [("num_envs", "envs", "{:d}"), ("physics_steps_per_s", "physics/s", "{:,.0f}"),
            ("collect_steps_per_s", "collect/s", "{:,.0f}"), ("train_steps_per_s", "train/s", "{:,.0f}"),
            ("collect_over_physics", "b/a", "{:.2f}"), ("train_over_physics", "c/a", "{:.2f}"),
            ("mem_used_gib", "GiB", "{:.2f}")]
    lines = [" | ".join(h for _, h, _ in cols)]
    for r in runs:
        lines.append(" | ".join(f.format(r[k]) if r.get(k) is not None else "-" for k, _, f in cols))
    for r in runs:
        if "ppo_update_s" in r:
            lines.append(f"PPO iteration at {r['num_envs']} envs: {r['iteration_s']:.3f} s, of which the update "
                         f"{r['ppo_update_s']:.3f} s (median of separately timed updates)")
        if "breakdown_ms" in r:
            lines.append(f"breakdown at {r['num_envs']} envs (ms per env step): "
                         + ", ".join(f"{k} {v:.3f}" for k, v in r["breakdown_ms"].items()))
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
