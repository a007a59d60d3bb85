"""`python -m bmimic.bench`: throughput of physics, collection and full PPO iterations.

    python -m bmimic.bench --envs 1024,4096,8192,16384                  # on the GPU
    python -m bmimic.bench --envs 8 --iters 3 --device cpu              # smoke test
    python -m bmimic.bench --envs 4096 --only sim -- motion=lafan_dance1   # Hydra overrides after --

For each env count, in one process on one device:
  (a) physics alone: the captured control-step graph (decimation physics steps + kinematics);
  (b) collection: environment steps with policy inference, as in a PPO rollout;
  (c) full PPO iterations: collection plus the update;
plus device memory, the ratios b/a and c/a, and a breakdown of one environment step (physics,
kinematics, observation, reward and termination terms, sampler update, resets, policy) and the PPO
update per iteration, each timed in isolation with device synchronisation through the parts' public
interfaces. Prints a table and writes JSON (--json).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from importlib.metadata import version

import torch


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


def bench_one(num_envs: int, device: str, iters: int, only: set[str], overrides: list[str]) -> dict:
    from hydra import compose, initialize_config_dir

    import bmimic.config  # noqa: F401
    from bmimic import CONF_DIR
    from bmimic.config import resolve_runtime
    from bmimic.runtime import seed_everything
    from bmimic.task import build_trainer, build_training

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train", overrides=[f"num_envs={num_envs}", f"device={device}", *overrides])
    resolve_runtime(cfg, device)
    seed_everything(cfg.seed)
    mem0 = _mem_used(device)
    t0 = time.perf_counter()
    training = build_training(cfg, device)
    env, layout, motion = training.env, training.task.layout, training.task.motion
    setup_s = time.perf_counter() - t0
    out: dict = {"num_envs": num_envs, "num_bins": layout.num_bins, "motion_s": motion.duration_s,
                 "setup_s": setup_s, "cuda_graph": bool(env.sim.use_graph),
                 "compile_env_step": bool(cfg.sim.compile_env_step)}
    n = num_envs
    sim_steps = max(iters * 10, 20)

    if "sim" in only:
        out["physics_steps_per_s"] = n / _timeit(env.sim.step, sim_steps, device)

    # The trainer builds the algorithm as training does; it never writes (no learn, no checkpoint).
    alg = build_trainer(training, None, tempfile.mkdtemp(prefix="bmimic-bench-")).alg
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
        out["mem_used_gib"] = _mem_used(device) - (mem0 or 0.0)
        out["torch_max_allocated_gib"] = torch.cuda.max_memory_allocated() / 2**30
    if "physics_steps_per_s" in out:
        for k in ("collect_steps_per_s", "train_steps_per_s"):
            if k in out:
                out[k.replace("_steps_per_s", "_over_physics")] = out[k] / out["physics_steps_per_s"]
    return out


def breakdown(env, alg, device: str, n: int) -> dict[str, float]:
    """Milliseconds per environment step spent in each part, each timed alone through its public
    interface (the term functions of the env's term tables, the sampler, the accounting). `resets`
    puts every world back on the reference (`reset_to_frames`: reference state, kinematics,
    observations), the most a step's masked resets can cost."""
    ones = torch.ones(env.num_envs, dtype=torch.bool, device=env.device)
    zeros = torch.zeros_like(ones)
    acc = env.accounting
    length = env.episode_length_buf
    obs = env.get_observations()

    def terms(table):
        return lambda: [fn(env, **p) for fn, p in zip(table.funcs, table.params)]

    parts = {
        "physics": env.sim.step,
        "kinematics_after_writes": env.sim.forward_kinematics,
        "observations": lambda: (terms(env.policy_terms)(), terms(env.critic_terms)()),
        "rewards": terms(env.reward_terms),
        "terminations": terms(env.termination_terms),
        # Counting every env as finished, plus one sampler update (each step for update_every=step,
        # once per iteration for update_every=iteration).
        "sampler_update": lambda: env.sampler.update_counts(
            *acc.count(ones, zeros, env.time_steps, env.segment_start, zeros, zeros, length)),
        "resets": lambda: env.reset_to_frames(env.time_steps.clone()),
        "policy": lambda: alg.act(obs),
    }
    out = {}
    with torch.inference_mode():
        for name, fn in parts.items():
            out[name] = 1000.0 * _timeit(fn, n, device)
        out["env_step_total"] = 1000.0 * _timeit(lambda: env.step(torch.zeros(env.num_envs, env.num_actions, device=env.device)), n, device)
    return out


def environment_info(device: str) -> dict:
    info = {"python": platform.python_version(), "date": time.strftime("%Y-%m-%d"), "device": device}
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
    p.add_argument("--json", default=None, help="write the results here")
    args = p.parse_args(argv)
    from bmimic.runtime import resolve_device

    device = resolve_device(args.device)
    only = set(args.only.split(","))
    results = {"environment": environment_info(device), "overrides": overrides, "runs": []}
    for n in [int(x) for x in args.envs.split(",")]:
        r = bench_one(n, device, args.iters, only, overrides)
        results["runs"].append(r)
        print(json.dumps(r), flush=True)
    print(format_table(results["runs"]))
    if args.json:
        from bmimic.run_folder import atomic_write_json

        atomic_write_json(args.json, results)
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
