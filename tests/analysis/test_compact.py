"""analysis.compact: a compacted run gives the same report, byte for byte, and keeps only what it reads."""

from __future__ import annotations

import shutil

import pandas as pd
import pyarrow.parquet as pq

from analysis.compact import compact_run, main
from analysis.report import build_report
from analysis.run_files import REPORT_COLUMNS
from tests.analysis.synthetic_runs import make_knob_study


def test_compacted_runs_rebuild_the_same_report(tmp_path):
    sweep = make_knob_study(tmp_path / "a")
    for run in sweep.glob("*/seed=*"):  # a column no report reads, as training writes many
        df = pd.read_parquet(run / "train_metrics.parquet")
        df.assign(**{"loss/value": 1.5}).to_parquet(run / "train_metrics.parquet", index=False)
    copy = tmp_path / "b" / "knobs"
    shutil.copytree(sweep, copy)
    assert main([str(copy)]) == 0
    run = next(copy.glob("*/seed=0"))
    assert set(pq.read_schema(run / "train_metrics.parquet").names) == set(REPORT_COLUMNS["train_metrics"])
    assert pd.read_parquet(run / "eval.parquet").equals(pd.read_parquet(sweep / run.relative_to(copy) / "eval.parquet"))
    a = build_report([sweep], out=tmp_path / "a" / "report")
    b = build_report([copy], out=tmp_path / "b" / "report")
    text_a = (a / "report.md").read_text().replace(str(sweep), "SWEEP")
    assert text_a == (b / "report.md").read_text().replace(str(copy), "SWEEP")
    for png in a.glob("*.png"):
        assert png.read_bytes() == (b / png.name).read_bytes(), png.name


def test_check_writes_nothing_and_a_bad_table_is_one_line(tmp_path, capsys):
    sweep = make_knob_study(tmp_path)
    run = next(sweep.glob("*/seed=0"))
    before = (run / "train_metrics.parquet").read_bytes()
    assert main([str(sweep), "--check"]) == 0
    assert (run / "train_metrics.parquet").read_bytes() == before
    assert "would shrink" in capsys.readouterr().out
    (run / "eval.parquet").write_bytes(b"not parquet")
    assert main([str(sweep)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "eval.parquet" in err[0]
    b, a = compact_run(next(sweep.glob("*/seed=1")), write=False)
    assert 0 < a < b


def test_records_lose_the_machines_paths(tmp_path):
    import json

    from analysis.compact import portable_records
    sweep = make_knob_study(tmp_path)
    run = next(sweep.glob("*/seed=0"))
    (run / ".hydra" / "hydra.yaml").write_text("hydra:\n  runtime:\n    cwd: /srv/box/repo\n    output_dir: /srv/box/repo/out\n")
    summary = {"checkpoint": "/srv/box/repo/outputs/s/seed=0/checkpoints/latest.pt", "run_dir": "/srv/box/repo",
               "elsewhere": "/srv/box/repository/x", "inside": "see /srv/box/repo/a", "n": 3}
    (run / "eval" / "whole_clip").mkdir(parents=True)
    (run / "eval" / "whole_clip" / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    untouched = (run / "metrics.json").read_bytes()
    assert portable_records(run, write=False) == 2 and (run / ".hydra" / "hydra.yaml").is_file()  # --check
    assert main([str(sweep)]) == 0
    got = json.loads((run / "eval" / "whole_clip" / "summary.json").read_text())
    assert got == {**summary, "checkpoint": "outputs/s/seed=0/checkpoints/latest.pt", "run_dir": "."}
    assert not (run / ".hydra" / "hydra.yaml").exists() and (run / ".hydra" / "config.yaml").is_file()
    assert (run / "metrics.json").read_bytes() == untouched
    assert portable_records(run) == 0  # done once


def test_a_data_folder_outside_the_checkout_becomes_the_variable_that_names_it(tmp_path):
    import json

    from analysis.compact import DATA_FOLDER_NAME, portable_records
    sweep = make_knob_study(tmp_path)
    run = next(sweep.glob("*/seed=0"))
    (run / ".hydra" / "hydra.yaml").write_text("hydra:\n  runtime:\n    cwd: /srv/box/repo\n")
    config = {"data": {"lafan_dir": "/tmp/lafan36"}, "motion": {"folder": "/tmp/lafan36", "other": "/tmp/lafan365/x"}}
    (run / "resolved_config.json").write_text(json.dumps(config, indent=2))
    (run / "s.json").write_text(json.dumps({"clip": "/tmp/lafan36/walk1.csv", "run_dir": "/srv/box/repo/o"}))
    assert portable_records(run) == 3
    got = json.loads((run / "resolved_config.json").read_text())
    assert got["data"]["lafan_dir"] == got["motion"]["folder"] == DATA_FOLDER_NAME
    assert got["motion"]["other"] == "/tmp/lafan365/x"  # another folder that only starts alike
    assert json.loads((run / "s.json").read_text()) == {"clip": f"{DATA_FOLDER_NAME}/walk1.csv", "run_dir": "o"}


def test_hydras_config_record_loses_the_folders_as_whole_values(tmp_path):
    import yaml

    from analysis.compact import DATA_FOLDER_NAME, portable_records
    sweep = make_knob_study(tmp_path)
    run = next(sweep.glob("*/seed=0"))
    (run / ".hydra" / "hydra.yaml").write_text("hydra:\n  runtime:\n    cwd: /srv/box/repo\n")
    (run / "resolved_config.json").write_text('{"data": {"lafan_dir": "/tmp/lafan36"}}')
    (run / ".hydra" / "config.yaml").write_text(
        "motion:\n  folder: /tmp/lafan36\n  near: /tmp/lafan365\n  clip: /tmp/lafan36/walk1.csv\n"
        "data:\n  lafan_dir: ${oc.env:BMIMIC_LAFAN_DIR,null}\nout: /srv/box/repo/outputs/x\nnote: see /tmp/lafan36\n")
    assert portable_records(run) == 3  # hydra.yaml, resolved_config.json, config.yaml
    got = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())
    assert got["motion"] == {"folder": DATA_FOLDER_NAME, "near": "/tmp/lafan365", "clip": f"{DATA_FOLDER_NAME}/walk1.csv"}
    assert got["out"] == "outputs/x" and got["data"]["lafan_dir"] == "${oc.env:BMIMIC_LAFAN_DIR,null}"
    assert got["note"] == "see /tmp/lafan36"  # only whole values are paths


def test_a_broken_record_is_one_line_and_the_run_keeps_its_hydra_record(tmp_path, capsys):
    sweep = make_knob_study(tmp_path)
    run = next(sweep.glob("*/seed=0"))
    (run / ".hydra" / "hydra.yaml").write_text("hydra:\n  runtime:\n    cwd: /srv/box/repo\n")
    (run / "a.json").write_text('{"run_dir": "/srv/box/repo/outputs/x"}')  # read before the broken one
    (run / "summary.json").write_text('{"run_dir": "/srv/box/repo/outputs/x", ')  # cut short
    assert main([str(run)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "summary.json: unreadable JSON record" in err and "\n" not in err
    assert (run / ".hydra" / "hydra.yaml").is_file()  # nothing half done: run it again once the file is mended
    assert (run / "a.json").read_text() == '{"run_dir": "/srv/box/repo/outputs/x"}'
    assert (run / "summary.json").read_text() == '{"run_dir": "/srv/box/repo/outputs/x", '


def test_survival_views_go_only_where_the_clips_and_failures_give_them_back(tmp_path, capsys):
    """A checkpoint's whole_clip_survival.csv that bmimic.runs.schema.whole_clip_survival derives back
    exactly is dropped; one that says something else (here a planted extra failure) stays; --check drops nothing."""
    import json

    from analysis.compact import drop_survival_views
    from bmimic.runs.folder import WHOLE_CLIP_FILES
    from bmimic.runs.schema import whole_clip_survival

    sweep = make_knob_study(tmp_path)
    run = next(sweep.glob("*/seed=0"))
    clips = pd.DataFrame([{"condition": "robust", "clip": 0, "clip_name": "dance", "clip_duration_s": 2.58,
                           "rollouts": 4, "completed": 3, "success_rate": 0.75, "transient_failures": 0,
                           "later_failures": 1}])
    failures = pd.DataFrame([{"condition": "robust", "clip": 0, "clip_name": "dance", "rollout": 2,
                              "failure_frame": 60, "failure_time_s": 1.2, "bin": 1, "transient": False,
                              "terminated": True, "broken": False}])
    folders = {}
    for label, edit in (("model_5", 0), ("model_9", 1)):
        folder = run / "eval" / label / "whole_clip"
        folder.mkdir(parents=True)
        survival = whole_clip_survival(clips, failures)
        survival.loc[survival.index[-1], "tracking"] -= edit  # model_9's view disagrees with its failures
        names = dict(zip(("clips", "survival", "failures", "summary"), WHOLE_CLIP_FILES, strict=True))
        clips.to_csv(folder / names["clips"], index=False)
        failures.to_csv(folder / names["failures"], index=False)
        survival.to_csv(folder / names["survival"], index=False)
        (folder / names["summary"]).write_text(json.dumps({"iteration": int(label.split("_")[1])}))
        folders[label] = folder / names["survival"]
    assert main([str(sweep), "--check"]) == 0 and all(p.is_file() for p in folders.values())
    assert "1 survival views would be dropped" in capsys.readouterr().out
    dropped, size = drop_survival_views(run)
    assert dropped == 1 and size > 0
    assert not folders["model_5"].is_file() and folders["model_9"].is_file()


def test_a_grown_table_keeps_its_earlier_row_groups_byte_for_byte():
    """A run continued across sittings commits its grown tables again: the rows of finished
    ROW_GROUP_ITERATIONS blocks come out as the same bytes, so git stores only the new rows."""
    import io

    import numpy as np
    import pyarrow as pa

    from analysis.compact import ROW_GROUP_ITERATIONS, compact_table, row_groups
    rng = np.random.default_rng(0)
    iterations = np.repeat(np.arange(0, 5 * ROW_GROUP_ITERATIONS, ROW_GROUP_ITERATIONS // 2) + 7, 40)
    full = pa.table({"iteration": iterations, "bin": np.tile(np.arange(40), len(iterations) // 40),
                     "failure_rate": rng.random(len(iterations))})
    earlier = full.filter(pa.compute.less(full["iteration"], 3 * ROW_GROUP_ITERATIONS + 300))
    a, b = compact_table(earlier, None), compact_table(full, None)
    assert pq.read_table(io.BytesIO(b)).equals(full) and pq.read_table(io.BytesIO(a)).equals(earlier)
    meta_a = pq.ParquetFile(io.BytesIO(a)).metadata
    assert meta_a.num_row_groups == 4 == len(row_groups(earlier))  # blocks 0, 1, 2 and the unfinished 3
    assert [meta_a.row_group(i).num_rows for i in range(4)] == [80, 80, 80, 80]
    chunk = meta_a.row_group(3).column(0)  # the unfinished block's first bytes
    finished = min(o for o in (chunk.dictionary_page_offset, chunk.data_page_offset) if o is not None)
    assert finished > 4 and a[:finished] == b[:finished]
    assert row_groups(pa.table({"bin": [1, 2]})) == [(0, 2)]
