"""Generated adversarial inputs (issue 36): hypothesis draws config overrides over the whole schema,
motion files (npz and CSV) and command-line flags, so that the next hundred cases are not written by
hand. One property throughout: bad input is one line naming the key, file or flag, through the
project's own error types, or it is accepted with a result that keeps the invariants; never another
exception (a traceback on the command line), never a write on refusal, never code run from a file.

Deterministic (derandomized, no example database) and sized for the default suite on two cores;
`pytest tests/test_generated_inputs.py -m slow` draws more of each. Each example runs the command's own
checks up to the first expensive step (composition, validation, motion loading, the task), not a
training.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.conftest import CONF

BASE = ["device=cpu", "num_envs=2", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2", "motion=easy_only",
        "motion.duration_s=7", "eval.horizon_s=0.2", "progress_bar=false", "logger=none", "max_iterations=1"]
FAST = settings(derandomize=True, database=None, deadline=None, max_examples=40,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
CHEAP = settings(FAST, max_examples=150)
"""For properties whose example costs milliseconds (motion files, CSVs)."""
MORE = settings(FAST, max_examples=300)
CASES: dict[str, int] = {}
"""Examples run per property (test_zz_report prints them: the harness's case count)."""


def one_line(e: BaseException) -> str:
    text = str(e).strip()
    assert text and "\n" not in text and "Traceback" not in text, repr(text)[:500]
    return text


def count(name: str) -> None:
    CASES[name] = CASES.get(name, 0) + 1


# --------------------------------------------------------------------------------------------- values
SPECIAL_NUMBERS = ["0", "-1", "1", "0.5", "1e-300", "1e300", "nan", "inf", "-inf", "2", "1000000000",
                   "18446744073709551616", "-0.0", "3.5"]
SPECIAL_TEXT = ["''", "' '", "'..'", "'../x'", "'a/b'", "'${oc.env:BMIMIC_UNSET_GENERATED}'", "'${oc.env:HOME}'",
                "nan", "true", "null", "'" + "x" * 300 + "'", "'\u00e9\u00e8'", "[]", "'{a: 1}'"]
SPECIAL_LISTS = ["[]", "[0]", "[1000000000]", "[nan]", "[1,2,3,4,5,6,7,8,9]", "['a']", "[-1]", "[inf, 1]"]


def _schema_keys() -> list[tuple[str, str]]:
    """(dotted key, kind) of every leaf of the composed default config: kind is number, text, bool
    or list; free-form term tables are included (their params too)."""
    from omegaconf import OmegaConf

    from tests.conftest import compose

    tree = OmegaConf.to_container(compose(BASE), resolve=False)
    out = []

    def walk(node, prefix):
        for k, v in node.items():
            key = f"{prefix}{k}"
            if isinstance(v, dict):
                walk(v, key + ".")
            elif isinstance(v, bool):
                out.append((key, "bool"))
            elif isinstance(v, (int, float)):
                out.append((key, "number"))
            elif isinstance(v, list):
                out.append((key, "list"))
            else:
                out.append((key, "text"))
    walk(tree, "")
    return sorted(out)


KEYS = _schema_keys()


@st.composite
def override(draw) -> str:
    key, kind = draw(st.sampled_from(KEYS))
    form = draw(st.sampled_from(["set", "set", "set", "delete", "add"]))
    if form == "delete":
        return f"~{key}"
    if form == "add":
        return f"+{key}.extra_{draw(st.integers(0, 9))}=1"
    pool = {"number": SPECIAL_NUMBERS, "bool": ["true", "false", "maybe", "0", "2"], "list": SPECIAL_LISTS,
            "text": SPECIAL_TEXT}[kind]
    value = draw(st.one_of(st.sampled_from(pool), st.sampled_from(SPECIAL_NUMBERS + SPECIAL_TEXT + SPECIAL_LISTS)))
    return f"{key}={value}"


def composed(overrides: list[str]):
    """The config Hydra composes for `python -m bmimic.train OVERRIDES` (Hydra's own errors raise)."""
    from hydra import compose, initialize_config_dir

    import bmimic.config  # noqa: F401

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=overrides, return_hydra_config=True)


def pre_training(cfg) -> None:
    """What `python -m bmimic.train` checks and builds before its environment, in its order
    (bmimic.train.main and train): check_composed, runtime resolution, validate, the task (robot,
    motion, bins) and the memory checks of the environment and the networks."""
    from bmimic import task as tasks
    from bmimic.config import resolve_runtime
    from bmimic.config.checks import check_composed, validate
    from bmimic.runtime import resolve_device

    check_composed(cfg, cfg.hydra.runtime.choices)
    device = resolve_device(cfg.device)
    resolve_runtime(cfg, device)
    validate(cfg, composed_checked=True)
    task = tasks.build_task(cfg, device)
    tasks.check_num_envs_fit(cfg, task.mjm, device, cfg.num_envs, cfg.ppo.num_steps_per_env)
    tasks.check_networks_fit(cfg, task.mjm, device)
    assert cfg.num_envs >= 1 and 0 <= cfg.max_iterations and math.isfinite(cfg.sim.timestep_s)
    assert task.motion.num_frames >= 2 and task.layout.num_bins >= 1


def _config_property(overrides: list[str], tmp_path: Path, monkeypatch) -> None:
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from bmimic.cli.common import user_errors

    monkeypatch.chdir(tmp_path)  # motion caches, if any, land here
    monkeypatch.delenv("BMIMIC_UNSET_GENERATED", raising=False)
    count("config overrides")
    from bmimic.config import check_additions

    try:  # the CLI's own check before Hydra composes (bmimic.train.cli)
        check_additions([*BASE, *overrides])
    except user_errors() as e:
        one_line(e)
        return
    try:
        cfg = composed([*BASE, *overrides])
    except (HydraException, OmegaConfBaseException):
        return  # refused by Hydra's grammar or the schema's types: the CLI prints Hydra's message
    try:
        pre_training(cfg)
    except user_errors() as e:
        one_line(e)  # anything else raised after composition is a finding (a traceback on the CLI)


@FAST
@given(overrides=st.lists(override(), min_size=1, max_size=3))
def test_generated_config_overrides_are_refused_in_one_line_or_build(overrides, tmp_path_factory, monkeypatch):
    _config_property(overrides, tmp_path_factory.mktemp("cfg"), monkeypatch)


@pytest.mark.slow
@MORE
@given(overrides=st.lists(override(), min_size=1, max_size=4))
def test_more_generated_config_overrides(overrides, tmp_path_factory, monkeypatch):
    _config_property(overrides, tmp_path_factory.mktemp("cfg"), monkeypatch)


# --------------------------------------------------------------------------------------------- motion files
@pytest.fixture(scope="module")
def motion_arrays(tmp_path_factory) -> dict:
    from bmimic.motion.config import MotionConfig, load_motion
    from bmimic.robot import load_mjmodel

    folder = tmp_path_factory.mktemp("motion")
    motion = load_motion(MotionConfig(source="builtin", builtin="easy_only", duration_s=7.0), load_mjmodel("g1"),
                         cache_dir=folder)
    motion.save(folder / "good.npz")
    with np.load(folder / "good.npz") as f:
        return {k: f[k] for k in f.files}


ARRAYS = ("joint_pos", "joint_vel", "body_pos_w", "body_quat_w", "body_lin_vel_w", "body_ang_vel_w")


@st.composite
def mutation(draw):
    key = draw(st.sampled_from([*ARRAYS, "fps", "joint_names", "body_names", "segments", "clip_starts"]))
    how = draw(st.sampled_from(["value", "scale", "dtype", "shape", "frames", "drop", "text"]))
    arg = draw(st.one_of(st.sampled_from([0.0, -1.0, 1e-300, 1e300, math.nan, math.inf, 2.0, 1e30, 50.0, 1e-9]),
                         st.floats(-1e6, 1e6, allow_nan=False)))
    text = draw(st.one_of(st.sampled_from(["", "[]", "{", "null", '[{"name": 1}]', '[{"name":"a","start_s":0,'
                                           '"end_s":1e308,"difficulty":"e"}]', "x" * 50]), st.text(max_size=30)))
    return key, how, arg, text, draw(st.integers(0, 10**6))


def _mutate(d: dict, m) -> None:
    key, how, arg, text, n = m
    if how == "drop":
        d.pop(key, None)
    elif how == "text":
        d[key] = np.asarray(text) if key == "segments" else np.asarray([text] * max(1, n % 4))
    elif key not in d:
        return
    elif how == "value":
        a = np.array(d[key], dtype=np.float64 if d[key].dtype.kind in "fiu" else d[key].dtype, copy=True)
        if a.dtype.kind == "f" and a.size:
            a.reshape(-1)[n % a.size] = arg
        d[key] = a
    elif how == "scale" and d[key].dtype.kind in "fiu":
        with np.errstate(all="ignore"):
            d[key] = d[key] * arg
    elif how == "dtype":
        kind = ["int8", "float16", "complex64", "bool", "U3", "int64"][n % 6]
        with np.errstate(all="ignore"), contextlib.suppress(ValueError, TypeError, OverflowError):
            d[key] = d[key].astype(kind)
    elif how == "shape" and d[key].ndim:
        d[key] = d[key].reshape(-1) if n % 2 else np.swapaxes(np.atleast_2d(d[key]), 0, -1)
    elif how == "frames" and key in ARRAYS:
        keep = n % 4
        for k in ARRAYS:
            if k in d and d[k].ndim:
                d[k] = d[k][:keep] if n % 3 else d[k][: keep + 1]


def _motion_property(arrays: dict, mutations: list, folder: Path) -> None:
    from bmimic.cli.common import user_errors
    from bmimic.motion.config import MotionConfig, load_motion
    from bmimic.robot import load_mjmodel

    count("motion npz files")
    d = {k: v.copy() for k, v in arrays.items()}
    for m in mutations:
        _mutate(d, m)
    path = folder / "m.npz"
    np.savez(path, **d)
    try:
        motion = load_motion(MotionConfig(source="file", path=str(path), name="m"), load_mjmodel("g1"),
                             cache_dir=folder / "cache", control_fps=50.0)
    except user_errors() as e:
        assert "m.npz" in one_line(e) or "motion" in str(e), str(e)
        return
    for k in ARRAYS:
        a = getattr(motion, k)
        assert a.shape[0] == motion.num_frames >= 2 and np.isfinite(a).all(), k
    assert motion.fps == 50.0
    np.testing.assert_allclose(np.linalg.norm(motion.body_quat_w, axis=-1), 1.0, atol=1e-3)


@CHEAP
@given(mutations=st.lists(mutation(), min_size=1, max_size=3))
def test_generated_motion_files_are_refused_in_one_line_or_load_valid(mutations, motion_arrays, tmp_path_factory):
    _motion_property(motion_arrays, mutations, tmp_path_factory.mktemp("npz"))


@pytest.mark.slow
@MORE
@given(mutations=st.lists(mutation(), min_size=1, max_size=5))
def test_more_generated_motion_files(mutations, motion_arrays, tmp_path_factory):
    _motion_property(motion_arrays, mutations, tmp_path_factory.mktemp("npz"))


# --------------------------------------------------------------------------------------------- CSV + convert flags
FLAG_VALUES = ["0", "-1", "nan", "inf", "1e-300", "1e300", "30", "50", "abc", "", "1e9", "2.5"]


@st.composite
def csv_and_flags(draw):
    rows = draw(st.integers(0, 50))
    cols = draw(st.sampled_from([36, 36, 36, 35, 37, 1]))
    fill = draw(st.sampled_from(["ok", "nan", "huge", "text", "empty_lines"]))
    flags = []
    for flag in draw(st.lists(st.sampled_from(["--fps-in", "--fps-out", "--frames"]), max_size=3, unique=True)):
        n = 2 if flag == "--frames" else 1
        flags += [flag, *[draw(st.sampled_from(FLAG_VALUES)) for _ in range(n)]]
    return rows, cols, fill, flags, draw(st.booleans())


def _convert_property(example, folder: Path) -> None:
    from bmimic.motion import convert

    count("convert CSV and flags")
    rows, cols, fill, flags, exists = example
    table = np.zeros((rows, cols))
    if cols >= 7:
        table[:, 2], table[:, 6] = 0.79, 1.0
    text = "\n".join(",".join(f"{v:.6f}" for v in row) for row in table) + "\n"
    if fill == "nan" and rows:
        text = text.replace("0.000000", "nan", 1)
    elif fill == "huge" and rows:
        text = text.replace("0.000000", "1e300", 1)
    elif fill == "text":
        text = "a,b,c\n" + text
    elif fill == "empty_lines":
        text = "\n\n" + text
    src, out = folder / "in.csv", folder / "out.npz"
    src.write_text(text)
    out.unlink(missing_ok=True)
    if exists:
        out.write_bytes(b"keep me")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        try:
            rc = convert.main([str(src), str(out), *flags])
        except SystemExit as e:  # argparse: its own one-line usage error, status 2
            rc = e.code
    said = buf.getvalue()
    assert "Traceback" not in said, said[-2000:]
    if rc == 0:
        from bmimic.motion.motion import Motion

        assert not exists and Motion.load(out, None).num_frames >= 2
    else:
        assert rc == 2 and [x for x in said.splitlines() if x.startswith(("error:", "usage:")) or "error:" in x], said
        assert (out.read_bytes() == b"keep me") if exists else not out.exists()


@CHEAP
@given(example=csv_and_flags())
def test_generated_csv_files_and_convert_flags(example, tmp_path_factory):
    _convert_property(example, tmp_path_factory.mktemp("csv"))


@pytest.mark.slow
@MORE
@given(example=csv_and_flags())
def test_more_generated_csv_files_and_convert_flags(example, tmp_path_factory):
    _convert_property(example, tmp_path_factory.mktemp("csv"))


# --------------------------------------------------------------------------------------------- eval, play, report flags
def _cli(main, argv: list[str]) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        try:
            rc = main(argv)
        except SystemExit as e:  # argparse: its own usage line, status 2
            rc = e.code
    return rc, buf.getvalue()


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    """A real run folder with a checkpoint (no training: max_iterations=0), for eval's flags."""
    from tests.conftest import train_in_process

    folder = tmp_path_factory.mktemp("trained")
    return train_in_process(folder / "run", *BASE[:-1], "max_iterations=0", "eval.every_iters=0", cwd=folder)


EVAL_FLAGS = {"--episodes-per-bin": ["0", "-3", "1", "100000000", "x"],
              "--horizon-s": ["nan", "inf", "-1", "0.2", "1e300"],
              "--max-envs": ["0", "-1", "2", "99999999999"], "--device": ["cpu", "gpu", "cuda:x", ""]}
BAD_EVAL = {"--episodes-per-bin": {"0", "-3", "100000000", "x"}, "--horizon-s": {"nan", "inf", "-1"},
            "--max-envs": {"0", "-1"}, "--device": {"gpu", "cuda:x", ""}}
"""The values of each flag that must be refused, naming the flag (or its config key)."""
EVAL_OVERRIDES = [f"{k}={v}" for k, kind in KEYS if k.startswith(("eval.", "seed", "env.episode_length"))
                  for v in ({"number": ["nan", "-1", "1e300"], "bool": ["maybe"], "list": ["[]"], "text": ["''"]}[kind])]


@st.composite
def eval_args(draw):
    flags = []
    for flag in draw(st.lists(st.sampled_from(sorted(EVAL_FLAGS)), max_size=3, unique=True)):
        flags += [flag, draw(st.sampled_from(EVAL_FLAGS[flag]))]
    return flags + draw(st.lists(st.sampled_from(EVAL_OVERRIDES), max_size=1))


def _names(flag: str) -> tuple[str, ...]:
    return flag, flag.lstrip("-").replace("-", "_")


@FAST
@given(args=eval_args())
def test_generated_eval_flags_and_overrides(trained_run, args):
    """A bad flag value is refused naming it; anything else evaluates (at most one short episode per
    bin here) and writes its tables, or is refused in one line, writing nothing."""
    import shutil

    from bmimic import eval as bm_eval

    count("eval flags and overrides")
    shutil.rmtree(trained_run / "eval", ignore_errors=True)
    flags = [a for a in args if "=" not in a]
    bad = [f for f, v in zip(flags[::2], flags[1::2]) if v in BAD_EVAL[f]]
    overridden = len(flags) < len(args)  # a bad override may then be the one named
    rc, said = _cli(bm_eval.main, [str(trained_run), *args])
    assert "Traceback" not in said, said[-2000:]
    if rc == 0:
        assert not bad, f"accepted {bad}: {said[-500:]}"
        assert len(list((trained_run / "eval").glob("*/eval_summary.json"))) == 1
        return
    errors = [x for x in said.splitlines() if x.startswith("error:") or ": error:" in x]
    assert rc == 2 and len(errors) == 1 and not (trained_run / "eval").exists(), said[-2000:]
    assert not bad or overridden or any(n in errors[0] for f in bad for n in _names(f)), (bad, errors[0])


@pytest.fixture(scope="module")
def saved_run(tmp_path_factory) -> Path:
    """A run folder as play reopens it, with an unreadable checkpoint: play checks its flags before
    reading anything, so an accepted set of flags ends at that one line (no OpenGL needed)."""
    from omegaconf import OmegaConf

    from tests.conftest import compose

    run = tmp_path_factory.mktemp("saved_run")
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(compose(BASE)))
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "latest.pt").write_bytes(b"not a checkpoint")
    return run


PLAY_FLAGS = {"--seconds": ["nan", "0", "-1", "1e9", "inf", "2"], "--fps": ["nan", "0", "1e9", "50"],
              "--width": ["0", "-5", "100000", "64"], "--height": ["0", "100000", "48"], "--start-s": ["nan", "-1", "999"]}
BAD_PLAY = {"--seconds": {"nan", "0", "-1", "1e9", "inf"}, "--fps": {"nan", "0", "1e9"},
            "--width": {"0", "-5", "100000"}, "--height": {"0", "100000"}}


@st.composite
def play_args(draw):
    flags = []
    for flag in draw(st.lists(st.sampled_from(sorted(PLAY_FLAGS)), max_size=3, unique=True)):
        flags += [flag, draw(st.sampled_from(PLAY_FLAGS[flag]))]
    return flags


@FAST
@given(args=play_args())
def test_generated_play_flags(saved_run, args):
    """A bad --seconds, --fps, --width or --height (not finite > 0, or frames that cannot fit in memory)
    is refused naming a flag before anything is read; the rest ends at the unreadable checkpoint."""
    from bmimic import play as bm_play
    from bmimic import render

    count("play flags")
    values = dict(zip(args[::2], args[1::2]))
    bad = [f for f, v in values.items() if v in BAD_PLAY.get(f, ())]
    saved, render.select_gl_backend = render.select_gl_backend, lambda *a, **k: "egl"
    try:
        rc, said = _cli(bm_play.main, [str(saved_run), *args])
    finally:
        render.select_gl_backend = saved
    errors = [x for x in said.splitlines() if x.startswith("error:")]
    assert rc == 2 and "Traceback" not in said and len(errors) == 1, said[-2000:]
    named = any(f in errors[0] for f in ("--seconds", "--fps", "--width", "--height"))
    assert named if bad else "latest.pt" in errors[0], (bad, errors[0])
    assert not (saved_run / "videos").exists()


REPORT_FLAGS = {"--resamples": ["0", "-5", "1", "20", "10000000", "x"], "--mastery-threshold": ["nan", "0", "2", "0.1"],
                "--success-threshold": ["-1", "1.5", "inf", "0.9"], "--mastery-persist": ["0", "-1", "2"]}


@st.composite
def report_args(draw):
    flags = []
    for flag in draw(st.lists(st.sampled_from(sorted(REPORT_FLAGS)), max_size=4, unique=True)):
        flags += [flag, draw(st.sampled_from(REPORT_FLAGS[flag]))]
    return flags


@FAST
@given(args=report_args())
def test_generated_report_options(args, tmp_path_factory):
    """Every option combination is refused in one line naming the flag, or reaches the runs (here a
    folder without any, the next line of refusal)."""
    from analysis import report

    count("report options")
    empty = tmp_path_factory.mktemp("no_runs")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        try:
            rc = report.main([str(empty), *args])
        except SystemExit as e:
            rc = e.code
    said = buf.getvalue()
    assert rc == 2 and "Traceback" not in said, said
    bad = [f for f, v in zip(args[::2], args[1::2]) if f in said]
    assert bad or "no run folders" in said, said
    assert list(empty.iterdir()) == []


def test_zz_report():
    """The harness's case count (run last in this module; pytest -s shows it)."""
    print("generated cases: " + json.dumps(CASES, sort_keys=True) + f" = {sum(CASES.values())}")
    assert sum(CASES.values()) > 0 or not CASES
