"""One policy for a folder of clips, end to end on the CPU: trained with `motion=lafan_folder` (one clip
held out), evaluated on the clip it never saw and on its own clips (`bmimic-eval RUN motion=...`), its
ONNX metadata saying how a clip and a frame are given to it, and sim2sim on one clip of it (`--clip`).
The clips are small CSVs in the LAFAN1 G1 format written by the test, never LAFAN1 data."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from bmimic import eval as bm_eval
from tests.conftest import TINY, train_in_process
from tests.motion.test_motion import _csv_rows, _write_csv

pytestmark = pytest.mark.slow
CLIPS = {"walk_a": 90, "walk_b": 105, "held_out": 120}
"""Rows at 30 Hz of each clip: 2.97, 3.47 and 3.97 s at 50 Hz (3, 4 and 4 one-second bins)."""


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    """(folder of the three clips, a tiny run trained on two of them)."""
    root = tmp_path_factory.mktemp("library")
    folder = root / "g1"
    folder.mkdir()
    for k, (name, rows) in enumerate(CLIPS.items()):
        table = _csv_rows(rows)
        table[:, 7 + 12] += 0.1 * k  # a different waist yaw per clip: different content, different cache entries
        _write_csv(folder / f"{name}.csv", table)
    run = train_in_process(root / "run", *[o for o in TINY if not o.startswith("motion=")], "motion=lafan_folder",
                           f"data.lafan_dir={folder}", "motion.exclude=[held_out]", "eval.episodes_per_bin=1",
                           "logger=none", cwd=root)
    return folder, run


def _summary(folder, name: str = "eval_summary.json") -> dict:
    return json.loads((folder / name).read_text())


def test_the_run_trains_on_the_selected_clips_with_bins_of_their_own(library):
    _, run = library
    ev = pd.read_parquet(run / "eval.parquet")
    assert sorted(set(ev["clip"])) == ["walk_a", "walk_b"] and len(ev) == 3 + 4  # 2.97 s and 3.47 s in 1 s bins


def test_eval_on_a_clip_the_policy_never_saw_is_one_command(library):
    folder, run = library
    assert bm_eval.main([str(run), f"motion={folder / 'held_out.csv'}"]) == 0
    (out,) = (run / "eval").glob("model_2_on_held_out-*")
    summary = _summary(out)
    assert summary["trained_on_motion"] is False and summary["motion"] == "held_out"
    assert summary["num_bins"] == 4 and summary["episodes"] == 4
    bins = pd.read_parquet(out / "eval_bins.parquet")
    assert list(bins["bin"]) == [0, 1, 2, 3] and set(bins["clip"]) == {"held_out"}
    assert not (run / "eval" / "model_2").exists()  # the training motion's evaluation is another folder


def test_eval_on_a_folder_and_on_the_training_clips(library):
    folder, run = library
    # every clip of the folder, the held-out one included: a library the policy saw two thirds of
    assert bm_eval.main([str(run), "motion=lafan_folder", f"data.lafan_dir={folder}"]) == 0
    (out,) = (run / "eval").glob("model_2_on_lafan_folder-*")
    assert _summary(out)["trained_on_motion"] is False
    assert _summary(out)["motion_clips"] == ["held_out", "walk_a", "walk_b"]
    segments = pd.read_csv(out / "eval_segments.csv")
    assert list(segments["segment"]) == ["held_out", "walk_a", "walk_b"]  # the per-clip table
    # the same selection as in training is the training motion: its own folder, as without an override
    assert bm_eval.main([str(run), "motion=lafan_folder", "motion.exclude=[held_out]",
                         f"data.lafan_dir={folder}"]) == 0
    assert _summary(run / "eval" / "model_2")["trained_on_motion"] is True


def test_a_motion_override_that_names_nothing_is_one_line(library, capsys):
    _, run = library
    assert bm_eval.main([str(run), "motion=no_such_option"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [err[0]] and err[0].startswith("error: override motion=no_such_option: neither a motion option")


def test_the_exported_policy_says_how_a_clip_and_a_frame_are_given(library):
    from bmimic.sim2sim.spec import read_metadata, read_policy

    _, run = library
    path = run / "checkpoints" / "motion_policy_2.onnx"
    meta, inputs, _ = read_metadata(path)
    assert inputs == ["obs", "time_step"]
    assert json.loads(meta["motion_clip_names"]) == ["walk_a", "walk_b"]
    assert meta["motion_clip_starts"] == "0,149" and meta["motion_num_frames"] == str(149 + 174)
    assert "motion_clip_starts[k]" in meta["time_step_input"] and "no clip id" in meta["time_step_input"]
    spec = read_policy(path)
    assert spec.clip_names == ["walk_a", "walk_b"] and spec.clip_starts.tolist() == [0, 149]


def test_sim2sim_runs_one_clip_of_the_library(library, capsys):
    from bmimic.sim2sim import main as sim2sim_main

    _, run = library
    assert bm_eval.main([str(run)]) == 0  # the MuJoCo-Warp evaluation the gap compares against
    assert sim2sim_main([str(run), "--clip", "walk_b", "--workers", "1"]) == 0
    out = run / "sim2sim" / "bmimic_g1" / "model_2_clip_walk_b"
    summary = _summary(out)
    assert summary["clips"] == ["walk_b"] and summary["num_bins"] == 4 and summary["episodes"] == 4
    episodes = pd.read_parquet(out / "eval_episodes.parquet")
    assert episodes["start_frame"].between(149, 149 + 174 - 1).all()  # only walk_b's frames
    assert sorted(episodes["bin"]) == [3, 4, 5, 6]  # the library's bin numbers
    gap = pd.read_csv(out / "sim2sim_gap_bins.csv")
    assert list(gap["bin"]) == [3, 4, 5, 6] and (gap["warp_visits"] > 0).all()
    assert "4 of its bins" in summary["warp_source"]
    warp_bins = pd.read_parquet(run / "eval" / "model_2" / "eval_bins.parquet").set_index("bin").loc[[3, 4, 5, 6]]
    assert summary["warp_success_rate"] == pytest.approx(1 - warp_bins["failures"].sum() / 4)
    assert not np.isnan(summary["gap_success_rate"])
    # an unknown clip is one line naming the clips there are
    capsys.readouterr()
    assert sim2sim_main([str(run), "--clip", "walk_c", "--workers", "1"]) == 2
    assert "--clip walk_c: no clip 'walk_c' in its motion (2 clips: walk_a, walk_b)" in capsys.readouterr().err


def test_whole_clips_of_an_unseen_clip_and_of_one_clip_in_native_mujoco(library):
    from bmimic.sim2sim import main as sim2sim_main

    folder, run = library
    assert bm_eval.main([str(run), "--whole-clip", "1", "--conditions", "robust", f"motion={folder / 'held_out.csv'}"]) == 0
    (out,) = (run / "eval").glob("model_2_on_held_out-*/whole_clip")
    assert _summary(out, "whole_clip_summary.json")["trained_on_motion"] is False
    assert list(pd.read_csv(out / "whole_clip.csv")["clip_name"]) == ["held_out"]
    # sim2sim's whole clips of one clip of the library: its name from the ONNX metadata, its library number
    assert sim2sim_main([str(run), "--whole-clip", "1", "--conditions", "nominal", "--clip", "walk_b",
                         "--workers", "1"]) == 0
    native = run / "sim2sim" / "bmimic_g1" / "model_2_clip_walk_b" / "whole_clip"
    assert _summary(native)["clips"] == ["walk_b"]
    rollouts = pd.read_parquet(native / "eval_episodes.parquet")
    assert list(zip(rollouts["clip"], rollouts["clip_name"], rollouts["start_frame"])) == [(1, "walk_b", 149)]
