"""Sampler-independent evaluation: stratified start frames in every bin, deterministic policy.

Training-time failure statistics are biased by the sampler (adaptive arms visit hard bins more), so
"when is a bin mastered" is measured here instead: `episodes_per_bin` episodes start at evenly spaced
frames inside each bin, run the deterministic policy for `horizon_s` (or to the end of the clip), and
an episode that terminates before then is a failure of the bin it started in. Tracking errors are
averaged over the steps an episode is alive.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import torch

from bmimic.envs.quat import quat_error_magnitude


def stratified_start_frames(bin_first_frame: np.ndarray, bin_num_frames: np.ndarray, per_bin: int) -> np.ndarray:
    """[S * per_bin] frames: per bin, the centres of `per_bin` equal slices of its frames."""
    k = (np.arange(per_bin) + 0.5) / per_bin
    offsets = np.floor(k[None, :] * bin_num_frames[:, None]).astype(np.int64)
    return (bin_first_frame[:, None] + offsets).reshape(-1)


ERROR_COLUMNS = (
    "mpkpe_mm", "mpkpe_rel_mm", "anchor_ori_err_rad", "body_ori_err_rad", "joint_pos_err_rad",
    "joint_vel_err_radps", "ee_pos_err_mm",
)


class Evaluator:
    """Runs evaluation episodes in a dedicated `mode="eval"` environment."""

    def __init__(self, env, layout, segments, episodes_per_bin: int, horizon_s: float) -> None:
        self.env = env
        self.layout = layout
        self.segments = list(segments)
        first = layout.bin_first_frame.cpu().numpy()
        count = layout.bin_num_frames.cpu().numpy()
        self.frames = stratified_start_frames(first, count, episodes_per_bin)
        self.bins = np.repeat(np.arange(layout.num_bins), episodes_per_bin)
        self.horizon_steps = max(1, int(round(horizon_s / env.step_dt)))

    def segment_of_bin(self) -> list[str]:
        """Label of each bin: the segment covering the bin's midpoint ('' without a manifest)."""
        edges = self.layout.edges_s.cpu().numpy()
        labels = []
        for b in range(self.layout.num_bins):
            mid = 0.5 * (edges[b] + edges[b + 1])
            name = ""
            for seg in self.segments:
                if seg.start_s <= mid < seg.end_s or (b == self.layout.num_bins - 1 and seg.end_s >= mid):
                    name = seg.name
                    break
            labels.append(name)
        return labels

    @torch.inference_mode()
    def run_episodes(self, policy) -> pd.DataFrame:
        """One row per evaluation episode: bin, start_frame, failed, steps and mean errors."""
        env = self.env
        n = env.num_envs
        rows = []
        for start in range(0, len(self.frames), n):
            frames = self.frames[start : start + n]
            m = len(frames)
            padded = np.concatenate([frames, np.full(n - m, frames[-1])])
            env.reset_to_frames(torch.as_tensor(padded, device=env.device))
            in_wave = torch.arange(n, device=env.device) < m
            alive = in_wave.clone()
            failed = torch.zeros(n, dtype=torch.bool, device=env.device)
            steps = torch.zeros(n, device=env.device)
            sums = torch.zeros(n, len(ERROR_COLUMNS), device=env.device)
            obs = env.get_observations()
            for _ in range(self.horizon_steps):
                actions = policy(obs, stochastic_output=False)
                obs, _, _, extras = env.step(actions)
                alive_f = alive.float()
                sums += _errors(env) * alive_f[:, None]
                steps += alive_f
                terminated = extras["terminated"] & alive
                failed |= terminated
                alive &= ~terminated & ~env.reached_clip_end
            means = (sums / steps.clamp_min(1)[:, None]).cpu().numpy()
            wave = pd.DataFrame(means[:m], columns=list(ERROR_COLUMNS))
            wave.insert(0, "steps", steps[:m].cpu().numpy().astype(int))
            wave.insert(0, "failed", failed[:m].cpu().numpy())
            wave.insert(0, "start_frame", frames)
            wave.insert(0, "bin", self.bins[start : start + m])
            rows.append(wave)
        return pd.concat(rows, ignore_index=True)

    def evaluate(self, policy, iteration: int, env_steps: int, wall_time_s: float) -> pd.DataFrame:
        """Per-bin table (eval.parquet rows) for one evaluation."""
        episodes = self.run_episodes(policy)
        grouped = episodes.groupby("bin")
        per_bin = grouped[list(ERROR_COLUMNS)].mean()
        per_bin["failures"] = grouped["failed"].sum()
        per_bin["episodes"] = grouped["failed"].count()
        per_bin = per_bin.reset_index()
        edges = self.layout.edges_s.cpu().numpy()
        labels = self.segment_of_bin()
        per_bin["failure_rate"] = per_bin["failures"] / per_bin["episodes"]
        per_bin.insert(0, "segment", [labels[b] for b in per_bin["bin"]])
        per_bin.insert(0, "bin_end_s", edges[per_bin["bin"] + 1])
        per_bin.insert(0, "bin_start_s", edges[per_bin["bin"]])
        per_bin.insert(0, "wall_time_s", float(wall_time_s))
        per_bin.insert(0, "env_steps", int(env_steps))
        per_bin.insert(0, "iteration", int(iteration))
        per_bin["failures"] = per_bin["failures"].astype(int)
        per_bin["episodes"] = per_bin["episodes"].astype(int)
        return per_bin


def _errors(env) -> torch.Tensor:
    """[N, len(ERROR_COLUMNS)] per-step tracking errors of the current state."""
    s = env.state
    a = env.anchor_index
    ee = env.end_effector_index
    body_err = (s.ref_body_pos - s.robot_body_pos).norm(dim=-1)
    ref_rel = s.ref_body_pos - s.ref_anchor_pos[:, None]
    rob_rel = s.robot_body_pos - s.robot_anchor_pos[:, None]
    rel_err = (ref_rel - rob_rel).norm(dim=-1)
    return torch.stack(
        (
            1000.0 * body_err.mean(-1),
            1000.0 * rel_err.mean(-1),
            quat_error_magnitude(s.ref_body_quat[:, a], s.robot_body_quat[:, a]),
            quat_error_magnitude(s.ref_body_quat_relative, s.robot_body_quat).mean(-1),
            (s.ref_joint_pos - s.joint_pos).abs().mean(-1),
            (s.ref_joint_vel - s.joint_vel).abs().mean(-1),
            1000.0 * (s.ref_body_pos_relative[:, ee] - s.robot_body_pos[:, ee]).norm(dim=-1).mean(-1),
        ),
        dim=-1,
    )


def summarize(per_bin: pd.DataFrame) -> dict[str, float]:
    """Overall numbers of one evaluation (episode-weighted)."""
    episodes = per_bin["episodes"].sum()
    out = {
        "eval_failure_rate": float(per_bin["failures"].sum() / max(episodes, 1)),
        "eval_bins_mastered_frac": float((per_bin["failure_rate"] < 0.1).mean()),
    }
    out["eval_success_rate"] = 1.0 - out["eval_failure_rate"]
    for c in ERROR_COLUMNS:
        v = float(np.average(per_bin[c], weights=per_bin["episodes"])) if episodes else math.nan
        out[f"eval_{c}"] = v
    return out
