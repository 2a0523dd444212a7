"""Issue #15: every bad input is a one-line ``error: ...`` with exit 2 and nothing written.

The matrix runs every subcommand through click's CliRunner in an empty working directory, with
inputs prepared once per module outside it: bad files (text, HDF5 with the wrong keys or shapes),
NaN / inf, too few points, degenerate data, unwritable outputs (a path under a regular file, /proc)
and bad ``--set`` / params.yaml values. Each case asserts exit code 2, one stderr line starting with
``error:`` that contains the expected fragment, no traceback, and an unchanged working directory.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from rlsac import config
from rlsac.cli import cli
from rlsac.data.lines import LineDataConf, generate, write
from rlsac.errors import RlsacError
from rlsac.sac import SACConf
from rlsac.train import TrainConf

PROC = "/proc/rlsac-no-such-dir"  # cannot be created, not even by root


def _lines(path, n=6, n_points=20, seed=1, **edit):
    conf = LineDataConf(outlier_rate=0.3, n_instances=max(n, 1), n_points=n_points, seed=seed)
    data = generate(conf) if n > 0 else {"points": np.zeros((0, n_points, 2), np.float32),
                                         "line": np.zeros((0, 3)), "inlier_mask": np.zeros((0, n_points), bool)}
    for k, fn in edit.items():
        data[k] = fn(data[k])
    write(path, data, conf)
    return path


def _nan(a):
    a = a.copy()
    a[0, 0, 0] = np.nan
    return a


def _inf(a):
    a = a.copy()
    a[1, 3, 1] = np.inf
    return a


def _identical(a):
    a = a.copy()
    a[2] = a[2, 0]
    return a


def _fundamental(root: Path) -> Path:
    """A small prepared fundamental file (test_tutorial's synthetic scene)."""
    from test_tutorial import N_POINTS, make_scene  # tests/ is on sys.path (pytest prepend mode)

    from rlsac.data.tutorial import PrepareConf, prepare

    make_scene(root / "raw")
    out = root / "fund.h5"
    prepare(PrepareConf(root=str(root / "raw"), split="val", scenes="s1", n_points=N_POINTS, out=str(out)),
            track=False, progress=False)
    return out


def _copy_h5(src: Path, dst: Path, **edit) -> Path:
    with h5py.File(src) as f, h5py.File(dst, "w") as g:
        for k in f:
            v = f[k][()]
            g[k] = edit[k](v) if k in edit else v
        g.attrs.update(dict(f.attrs))
    return dst


def _zero_first(a):
    a = a.copy()
    a[0] = 0
    return a


def _same_coords(a):
    a = a.copy()
    a[1] = a[1, 0]
    return a


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    f = {"dir": d}
    f["lines"] = _lines(d / "lines.h5")
    f["lines_nan"] = _lines(d / "lines_nan.h5", points=_nan)
    f["lines_inf"] = _lines(d / "lines_inf.h5", points=_inf)
    f["lines_empty"] = _lines(d / "lines_empty.h5", n=0)
    f["lines_degenerate"] = _lines(d / "lines_degenerate.h5", points=_identical)
    f["lines_one_point"] = d / "lines_one_point.h5"
    with h5py.File(f["lines_one_point"], "w") as h:
        h["points"], h["line"], h["inlier_mask"] = np.ones((3, 1, 2)), np.ones((3, 3)), np.ones((3, 1), bool)
    f["lines_shape"] = d / "lines_shape.h5"
    with h5py.File(f["lines_shape"], "w") as h:
        h["points"], h["line"], h["inlier_mask"] = np.ones((3, 20, 3)), np.ones((3, 3)), np.ones((3, 20), bool)
    f["lines_wrong_key"] = d / "lines_wrong_key.h5"
    with h5py.File(f["lines_wrong_key"], "w") as h:
        h["pts"] = np.ones((3, 20, 2))
    f["text"] = d / "notes.txt"
    f["text"].write_text("not a checkpoint, not hdf5\n")
    f["text_h5"] = d / "text.h5"
    f["text_h5"].write_text("not hdf5\n")
    f["blocker"] = d / "blocker"  # a regular file: nothing can be written under it
    f["blocker"].write_text("x")
    f["fund"] = _fundamental(d)
    f["fund_singular"] = _copy_h5(f["fund"], d / "fund_singular.h5", K1=_zero_first)
    f["fund_degenerate"] = _copy_h5(f["fund"], d / "fund_degenerate.h5", coords=_same_coords)
    f["fund_nan"] = _copy_h5(f["fund"], d / "fund_nan.h5", coords=_nan)
    params = {
        "p_missing": None,
        "p_list": "- a\n- b\n",
        "p_scalar": "3\n",
        "p_yaml": "train: [unclosed\n",
        "p_lines_key": "lines_data:\n  bogus: 1\n",
        "p_lines_band": "lines_data:\n  band: abc\n",
        "p_lines_section": "lines_data: 5\n",
        "p_train_steps": "train:\n  line:\n    sac: {total_steps: abc}\n",
        "p_train_sac": "train:\n  line:\n    sac: 5\n",
        "p_eval_iter": "evaluate:\n  line:\n    iterations: abc\n",
        "p_lines_n": "lines:\n  n_train: -4\n",
        "p_folds_pool": "folds:\n  pool: {easy: 0, hard: x}\n",
        "p_folds_iter": "folds:\n  iterations: [x]\n",
        "p_folds_iter_scalar": "folds:\n  iterations: 100\n",
        "p_folds_seed": "folds:\n  seed: -1\n",
        "p_folds_val": "folds:\n  val_fraction: 1.5\n",
    }
    for name, text in params.items():
        f[name] = d / f"{name}.yaml"
        if text is not None:
            f[name].write_text(text)
    for name, content in {"ev_empty": "", "ev_invalid": "{not json", "ev_list": "[1, 2]"}.items():
        p = d / name / "lines" / "ransac" / "o0.5" / "summary.json"
        p.parent.mkdir(parents=True)
        p.write_text(content)
        f[name] = p.parents[3]
    p = d / "ev_nocol" / "lines" / "ransac" / "o0.5"
    p.mkdir(parents=True)
    (p / "summary.json").write_text(json.dumps({"mAA": 0.5, "median_deg": 0.1}))
    (p / "errors.csv").write_text("instance,err\n0,0.1\n")
    f["ev_nocol"] = p.parents[2]
    f["state_text"] = d / "state_text.pt"
    f["state_text"].write_text("not a torch file")
    # a source scene whose images cannot be read: import-scenes fails after creating its folders
    src = d / "src_bad" / "mini"
    (src / "images").mkdir(parents=True)
    (src / "cameras").mkdir()
    camera = "100 0 50\n0 100 40\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n100 80\n"
    for i in ("0001", "0002"):
        (src / "images" / f"{i}.jpg").write_bytes(b"junk")
        (src / "cameras" / f"{i}.jpg.camera").write_text(camera)
    f["src_bad"] = src.parent
    return f


def _tree(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _arg(value, f):
    """'{name}' in an argument -> the path of input ``name``."""
    if isinstance(value, str) and "{" in value:
        return value.format(**{k: str(v) for k, v in f.items()}, proc=PROC)
    return str(value)


def train(*extra, data="{lines}", out="ck/m.pt", params=""):
    # a 1-step budget first (a case that wrongly passed validation would not train for minutes), except
    # where a params file is under test: --set would override it
    safety = [] if params else ["--set", "sac.total_steps=1"]
    return ["train", *safety, "--task", "line", "--data", data, "--out", out, "--params", params, *extra]


def evaluate(*extra, task="line", data="{lines}", out="ev", params=""):
    budget = [] if params else ["--iterations", "5"]  # a flag would override the params file under test
    return ["evaluate", "--task", task, "--method", "ransac", "--data", data, "--out-dir", out, "--params", params,
            *budget, *extra]


def rlsac_eval(checkpoint):
    return ["evaluate", "--task", "line", "--method", "rlsac", "--checkpoint", checkpoint, "--data", "{lines}",
            "--out-dir", "ev", "--params", ""]


def synth(*extra, out="d/x.h5", params=""):
    return ["synth-lines", "--n-instances", "3", "--out", out, "--params", params, *extra]


def cal(*extra, out="rep/cal", params=""):
    return ["calibrate-lines", "--n-instances", "5", "--n-seeds", "1", "--iterations", "5", "--out", out,
            "--params", params, *extra]


def lines_data(*extra, rate="0.3", out="lines", params=""):
    return ["lines-data", "--rate", rate, "--out-dir", out, "--params", params, *extra]


def imp(*extra, src="{src_bad}", out="raw"):
    return ["import-scenes", "--src", src, "--out", out, *extra]


def prep(*extra, root="{dir}/raw", out="f/val.h5"):
    return ["prepare-cvpr2020", "--root", root, "--split", "val", "--out", out, *extra]


EVAL_F = {"task": "fundamental"}

# (id, argv, fragment of the one-line message)
CASES = [
    # --- synth-lines: NaN / inf / range, unwritable output, params
    ("synth-band-nan", synth("--band", "nan"), "band must be a finite number"),
    ("synth-picture-inf", synth("--picture-size", "inf"), "picture_size must be a finite number"),
    ("synth-picture-0", synth("--picture-size", "0"), "picture_size must be in (0, inf)"),
    ("synth-band-neg", synth("--band", "-1"), "band must be in [0, inf)"),
    ("synth-seed-neg", synth("--seed", "-1"), "seed must be in [0, 4294967295]"),
    ("synth-outlier-1", synth("--outlier", "1"), "outlier rate must be in [0, 1)"),
    ("synth-outlier-nan", synth("--outlier", "nan"), "outlier_rate must be a finite number"),
    ("synth-too-few-points", synth("--n-points", "1"), "fewer than 2 inliers"),
    ("synth-out-under-file", synth(out="{blocker}/x.h5"), "is not a folder"),
    ("synth-out-proc", synth(out="{proc}/x.h5"), "cannot write output"),
    ("synth-params-missing", synth(params="{p_missing}"), "no such params file"),
    ("synth-params-list", synth(params="{p_list}"), "must be a mapping of sections, got list"),
    ("synth-params-scalar", synth(params="{p_scalar}"), "must be a mapping of sections, got int"),
    ("synth-params-yaml", synth(params="{p_yaml}"), "invalid YAML"),
    ("synth-params-key", synth(params="{p_lines_key}"), "unknown config key(s) ['bogus'] in lines_data"),
    ("synth-params-type", synth(params="{p_lines_band}"), "lines_data.band must be a number, got 'abc'"),
    ("synth-params-section", synth(params="{p_lines_section}"), "params section lines_data must be a mapping"),
    # --- lines-data: every argument checked before the first file is written
    ("lines-data-bogus-split", lines_data("--splits", "train,bogus"),
     "unknown split 'bogus'"),
    ("lines-data-rate", lines_data(rate="1.5"), "rate must be in [0, 1)"),
    ("lines-data-rate-nan", lines_data(rate="nan"), "finite"),
    ("lines-data-out", lines_data(out="{blocker}/lines"), "is not a folder"),
    ("lines-data-params-missing", lines_data(params="{p_missing}"), "no such params file"),
    ("lines-data-params-n", lines_data(params="{p_lines_n}"), "lines.n_train must be in [1, inf)"),
    # --- import-scenes
    ("import-max-features", imp("--max-features", "-5"), "max_features must be in [1, inf)"),
    ("import-max-features-0", imp("--max-features", "0"), "max_features must be in [1, inf)"),
    ("import-min-matches", imp("--min-matches", "-1"), "min_matches must be in [0, inf)"),
    ("import-set-type", imp("--set", "keep_snn=abc"), "keep_snn must be a number, got 'abc'"),
    ("import-set-nan", imp("--set", "keep_snn=.nan"), "keep_snn must be a finite number"),
    ("import-set-bool", imp("--set", "rootsift=3"), "rootsift must be true or false"),
    ("import-set-unknown", imp("--set", "bogus=1"), "unknown config key(s) ['bogus']"),
    ("import-out-under-file", imp(out="{blocker}/raw"), "is not a folder"),
    ("import-src-missing", imp(src="nowhere"), "no such source folder"),
    ("import-unreadable-image", imp(), "unreadable image"),  # fails mid-import: its folders are removed
    # --- prepare-cvpr2020
    ("prepare-max-pairs", prep("--max-pairs-per-scene", "-1"), "max_pairs_per_scene must be in [0, inf)"),
    ("prepare-n-points", prep("--n-points", "3"), "n_points must be at least 8"),
    ("prepare-n-points-type", prep("--set", "n_points=abc"), "n_points must be an integer, got 'abc'"),
    ("prepare-gt-nan", prep("--set", "gt_threshold=.inf"), "gt_threshold must be a finite number"),
    ("prepare-out-under-file", prep(out="{blocker}/val.h5"), "is not a folder"),
    ("prepare-out-proc", prep(out="{proc}/val.h5"), "cannot write output"),
    ("prepare-root-missing", prep(root="nowhere"),
     "nowhere"),
    # --- train: --set types and ranges, bad files, unwritable output, params
    ("train-actor-lr-abc", train("--set", "sac.actor_lr=abc"), "train.sac.actor_lr must be a number, got 'abc'"),
    ("train-actor-lr-neg", train("--set", "sac.actor_lr=-1"), "train.sac.actor_lr must be in (0, inf), got -1.0"),
    ("train-actor-lr-nan", train("--set", "sac.actor_lr=.nan"), "train.sac.actor_lr must be a finite number"),
    ("train-total-steps-abc", train("--set", "sac.total_steps=abc"), "sac.total_steps must be an integer"),
    ("train-total-steps-0", train("--set", "sac.total_steps=0"), "sac.total_steps must be in [1, inf)"),
    ("train-total-steps-frac", train("--set", "sac.total_steps=2.5"), "sac.total_steps must be an integer"),
    ("train-ckpt-every-0", train("--set", "ckpt_every=0"), "train.ckpt_every must be in [1, inf)"),
    ("train-val-every-0", train("--set", "val_every=0"), "train.val_every must be in [1, inf)"),
    ("train-steps-per-episode-0", train("--set", "env.steps_per_episode=0"), "env.steps_per_episode must be in"),
    ("train-num-envs-0", train("--set", "sac.num_envs=0"), "sac.num_envs must be in [1, inf)"),
    ("train-batch-size-0", train("--set", "sac.batch_size=0"), "sac.batch_size must be in [1, inf)"),
    ("train-val-instances-0", train("--set", "val_instances=0"), "train.val_instances must be in [1, inf)"),
    ("train-sac-scalar", train("--set", "sac=5"), "train.sac must be a mapping of SACConf options, got 5"),
    ("train-gamma", train("--set", "sac.gamma=2"), "sac.gamma must be in [0, 1]"),
    ("train-sampling", train("--set", "sac.train_sampling=greedy"), "sac.train_sampling must be one of prob, max"),
    ("train-widths", train("--set", "policy.widths=[32,0]"), "policy.widths[1] must be in [1, inf)"),
    ("train-resume-type", train("--set", "resume=3"), "train.resume must be true or false"),
    ("train-unknown", train("--set", "sac.bogus=1"), "unknown config key(s) ['bogus'] in train.sac"),
    ("train-task-options", train("--set", "task_options.bogus=1"), "bad task_options for task 'line'"),
    ("train-seed", train("--seed", "-1"), "train.seed must be in"),
    ("train-data-text", train(data="{text_h5}"), "not a readable HDF5 file"),
    ("train-data-missing", train(data="nope.h5"), "no such file"),
    ("train-data-empty", train(data="{lines_empty}"), "holds no instances"),
    ("train-data-degenerate", train(data="{lines_degenerate}"),
     "degenerate data: all 20 points of instance 2 are identical"),
    ("train-data-nan", train(data="{lines_nan}"), "contains NaN or inf"),
    ("train-data-shape", train(data="{lines_shape}"), "has shape (3, 20, 3)"),
    ("train-val-data-text", train("--val-data", "{text_h5}"), "not a readable HDF5 file"),
    ("train-out-under-file", train(out="{blocker}/m.pt"), "cannot write checkpoint"),
    ("train-out-proc", train(out="{proc}/m.pt"), "cannot write checkpoint"),
    ("train-params-missing", train(params="{p_missing}"), "no such params file"),
    ("train-params-type", train(params="{p_train_steps}"), "train.sac.total_steps must be an integer, got 'abc'"),
    ("train-params-sac", train(params="{p_train_sac}"), "train.sac must be a mapping"),
    ("train-resume-nothing", train("--resume"), "nothing to resume from"),
    # --- evaluate
    ("eval-data-text", evaluate(data="{text_h5}"), "not a readable HDF5 file"),
    ("eval-data-wrong-key", evaluate(data="{lines_wrong_key}"), "missing key 'points'"),
    ("eval-data-shape", evaluate(data="{lines_shape}"), "has shape (3, 20, 3)"),
    ("eval-data-nan", evaluate(data="{lines_nan}"), "key 'points' contains NaN or inf"),
    ("eval-data-inf", evaluate(data="{lines_inf}"), "key 'points' contains NaN or inf"),
    ("eval-data-empty", evaluate(data="{lines_empty}"), "holds no instances"),
    ("eval-data-one-point", evaluate(data="{lines_one_point}"), "at least 2 points"),
    ("eval-data-degenerate", evaluate(data="{lines_degenerate}"), "degenerate data"),
    ("eval-ckpt-text", rlsac_eval("{text}"), "not an rlsac checkpoint (UnpicklingError"),
    ("eval-ckpt-h5", rlsac_eval("{lines}"), "not an rlsac checkpoint"),
    ("eval-ckpt-unused", evaluate("--checkpoint", "{text}"), "--checkpoint is used by --method rlsac only"),
    ("eval-iterations-0", evaluate("--iterations", "0"), "iterations must be positive"),
    ("eval-batch-0", evaluate("--batch-size", "0"), "batch_size must be positive"),
    ("eval-steps-0", evaluate("--steps-per-episode", "0"), "steps_per_episode must be positive"),
    ("eval-seed", evaluate("--seed", "-1"), "seed must be in"),
    ("eval-policy-every-0", evaluate("--policy-every", "0"), "policy_every must be in [1, inf), got 0"),
    ("eval-sets-per-step-0", evaluate("--sets-per-step", "0"), "sets_per_step must be in [1, inf), got 0"),
    ("eval-confidence-1", evaluate("--confidence", "1"), "confidence must be in [0, 1), got 1.0"),
    ("eval-e-lines-file", evaluate(data="{lines}", task="essential"), "not a prepared file"),
    ("eval-e-oracle", evaluate("--method", "oracle", data="{fund}", task="essential"),
     "needs the true inlier mask in its data"),
    ("eval-out-under-file", evaluate(out="{blocker}/ev"), "is not a folder"),
    ("eval-out-proc", evaluate(out="{proc}/ev"), "cannot write output"),
    ("eval-params-missing", evaluate(params="{p_missing}"), "no such params file"),
    ("eval-params-list", evaluate(params="{p_list}"), "must be a mapping"),
    ("eval-params-type", evaluate(params="{p_eval_iter}"), "iterations must be an integer, got 'abc'"),
    ("eval-f-singular", evaluate(data="{fund_singular}", **EVAL_F), "key 'K1' row 0 (im-0-im1) is a singular matrix"),
    ("eval-f-degenerate", evaluate(data="{fund_degenerate}", **EVAL_F), "degenerate data: all valid correspondences"),
    ("eval-f-nan", evaluate(data="{fund_nan}", **EVAL_F), "key 'coords' contains NaN or inf"),
    ("eval-f-lines-file", evaluate(data="{lines}", **EVAL_F), "not a prepared file"),
    # --- calibrate-lines
    ("cal-seed", cal("--seed", "-1"), "seed must be in [0, 4294967295]"),
    ("cal-n-seeds", cal("--n-seeds", "0"), "n_seeds must be in [1, inf)"),
    ("cal-iterations", cal("--iterations", "0"), "iterations must be in [1, inf)"),
    ("cal-n-instances", cal("--n-instances", "0"), "counts must be positive"),
    ("cal-out-under-file", cal(out="{blocker}/cal"), "is not a folder"),
    ("cal-out-proc", cal(out="{proc}/cal"), "cannot write output"),
    ("cal-params-missing", cal(params="{p_missing}"), "no such params file"),
    ("cal-params-band", cal(params="{p_lines_band}"), "lines_data.band must be a number"),
    # --- table
    ("table-empty-summary", ["table", "--eval-root", "{ev_empty}", "--out-dir", "rep"],
     "ransac/o0.5/summary.json: not a valid summary.json (JSONDecodeError)"),
    ("table-invalid-summary", ["table", "--eval-root", "{ev_invalid}", "--out-dir", "rep"], "not a valid summary.json"),
    ("table-list-summary", ["table", "--eval-root", "{ev_list}", "--out-dir", "rep"], "holds a list, not a mapping"),
    ("table-no-error-column", ["table", "--eval-root", "{ev_nocol}", "--out-dir", "rep"],
     "errors.csv: no 'err_deg' column"),
    ("table-out-under-file", ["table", "--eval-root", "nowhere", "--out-dir", "{blocker}/rep"], "is not a folder"),
    # --- plot, ablate
    ("plot-unknown", ["plot", "--set", "bogus=1"], "unknown plot option"),
    ("plot-set-syntax", ["plot", "--set", "novalue"], "key=value"),
    ("ablate-train-steps", ["ablate", "--what", "sampling", "--train-steps", "0", "--params", ""],
     "train_steps must be positive"),
    ("ablate-params-missing", ["ablate", "--what", "sampling", "--params", "{p_missing}"], "no such params file"),
    ("ablate-unknown", ["ablate", "--what", "sampling", "--params", "", "--set", "bogus=1"], "unknown ablate option"),
    ("ablate-threads-type", ["ablate", "--what", "sampling", "--params", "", "--set", "threads=abc"],
     "ablate.threads must be an integer, got 'abc'"),
    ("ablate-threads-range", ["ablate", "--what", "sampling", "--params", "", "--set", "threads=-1"],
     "ablate.threads must be in [0, inf)"),
    ("ablate-table-type", ["ablate", "--what", "sampling", "--params", "", "--set", "table=5"],
     "ablate.table must be true or false"),
    ("plot-steps-type", ["plot", "--set", "line_steps=abc"], "plot.line_steps must be an integer, got 'abc'"),
    ("plot-steps-range", ["plot", "--set", "fundamental_steps=0"], "plot.fundamental_steps must be in [1, inf)"),
    ("plot-seed", ["plot", "--set", "seed=-1"], "plot.seed must be in"),
    # params.yaml folds: every key typed and range-checked at load, whatever the stage (a stage that does not read
    # a key still refuses it): data, train and evaluate alike
    ("folds-pool-type", ["folds", "--stage", "evaluate", "--regime", "hard", "--fold", "castle", "--params",
                         "{p_folds_pool}"], "folds.pool.hard must be an integer, got 'x'"),
    ("folds-iter-type", ["folds", "--stage", "data", "--regime", "hard", "--fold", "castle", "--params",
                         "{p_folds_iter}"], "folds.iterations must be an integer, got 'x'"),
    ("folds-iter-list", ["folds", "--stage", "train", "--regime", "hard", "--fold", "castle", "--params",
                         "{p_folds_iter_scalar}"], "folds.iterations must be a list, got 100"),
    ("folds-seed", ["folds", "--stage", "evaluate", "--regime", "hard", "--fold", "castle", "--params",
                    "{p_folds_seed}"], "folds.seed must be in [0, 4294967295]"),
    ("folds-val", ["folds", "--stage", "data", "--regime", "easy", "--fold", "entry", "--params", "{p_folds_val}"],
     "folds.val_fraction must be in (0, 1), got 1.5"),
    # click's own usage errors: the same one `error:` line (not click's four-line usage block), exit 2
    ("click-method", ["evaluate", "--task", "line", "--method", "bogus", "--data", "x.h5"],
     "Invalid value for '--method': 'bogus' is not one of"),
    ("click-which", ["table", "--which", "bogus"], "Invalid value for '--which'"),
    ("click-option", ["synth-lines", "--bogus", "1"], "No such option '--bogus'"),
    ("click-missing", ["evaluate", "--task", "line", "--data", "x.h5"], "Missing option '--method'"),
    ("click-command", ["nope"], "No such command 'nope'"),
    ("click-int", ["verify", "--sample", "many"], "Invalid value for '--sample'"),
]


@pytest.mark.parametrize("argv, fragment", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_error_and_writes_nothing(workdir, inputs, argv, fragment):
    before = _tree(workdir)
    inputs_before = _tree(inputs["dir"])
    r = CliRunner().invoke(cli, [_arg(a, inputs) for a in argv] + ["--no-tracking"])
    assert r.exit_code == 2, (r.exit_code, r.output, r.exception)
    err = r.stderr.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    assert "Traceback" not in r.output
    assert fragment in err, err
    assert _tree(workdir) == before  # nothing written, no empty folders either
    assert _tree(inputs["dir"]) == inputs_before


@pytest.mark.parametrize("argv", [synth(), evaluate(), train(), cal(), lines_data(),
                                  ["table", "--eval-root", "nowhere", "--out-dir", "rep"]],
                         ids=["synth-lines", "evaluate", "train", "calibrate-lines", "lines-data", "table"])
@pytest.mark.parametrize("store", ["{proc}/mlflow.db", "{blocker}/mlflow.db"], ids=["proc", "under-file"])
def test_unwritable_tracking_store_is_one_line_error(workdir, inputs, monkeypatch, argv, store):
    """Tracking on with a store that cannot be written (as in a read-only working directory)."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:///" + _arg(store, inputs))
    r = CliRunner().invoke(cli, [_arg(a, inputs) for a in argv])
    assert r.exit_code == 2, r.output
    err = r.stderr.strip()
    assert err.startswith("error: cannot write the MLflow store") and "\n" not in err, err
    assert "--no-tracking" in err
    assert _tree(workdir) == set()


# ------------------------------------------------------------------------------------------- config


def test_build_coerces_and_checks_every_field():
    c = config.build(TrainConf, {"sac": {"actor_lr": "1e-4", "total_steps": 1e3, "gamma": 1}, "seed": "3"})
    assert c.sac.actor_lr == 1e-4 and isinstance(c.sac.actor_lr, float)
    assert c.sac.total_steps == 1000 and isinstance(c.sac.total_steps, int)
    assert c.sac.gamma == 1.0 and isinstance(c.sac.gamma, float) and c.seed == 3
    for bad, message in [({"sac": {"batch_size": True}}, "must be an integer"),
                         ({"threads": -1}, "train.threads must be in [0, inf)"),
                         ({"tags": 3}, "train.tags must be a mapping"),
                         ({"policy": {"widths": 32}}, "train.policy.widths must be a list"),
                         ({"data": ["a"]}, "train.data must be a string")]:
        with pytest.raises(RlsacError) as e:
            config.build(TrainConf, bad, "train")
        assert message in str(e.value)
    with pytest.raises(RlsacError, match=r"SACConf must be a mapping"):
        config.build(SACConf, [1, 2])


def test_every_range_names_a_field():
    """A typo in a ``ranges`` key would silently check nothing."""
    import dataclasses

    from rlsac.data.lines import LineDataConf
    from rlsac.data.scenes import ImportConf
    from rlsac.data.tutorial import PrepareConf
    from rlsac.env import EnvConf
    from rlsac.policy import PolicyConf

    for cls in (TrainConf, SACConf, EnvConf, PolicyConf, LineDataConf, ImportConf, PrepareConf):
        names = {f.name for f in dataclasses.fields(cls)}
        assert set(cls.ranges) <= names, (cls.__name__, set(cls.ranges) - names)
        config.build(cls, {})  # the defaults pass their own checks
        for name, spec in cls.ranges.items():
            config.check_range(name, getattr(cls(), name), spec)


def test_import_failure_leaves_no_empty_folders(workdir, inputs):
    r = CliRunner().invoke(cli, ["import-scenes", "--src", str(inputs["src_bad"]), "--out", "a/b/raw",
                                 "--no-tracking"])
    assert r.exit_code == 2 and "unreadable image" in r.stderr
    assert not (workdir / "a").exists()


def test_lines_data_writes_nothing_when_a_later_split_is_bad(workdir):
    r = CliRunner().invoke(cli, ["lines-data", "--rate", "0.3", "--splits", "train,bogus", "--out-dir", "lines",
                                 "--params", "", "--no-tracking"])
    assert r.exit_code == 2 and "unknown split 'bogus'" in r.stderr
    assert not (workdir / "lines").exists()


# ---------------------------------------------------------------------------------- kill and resume

RESUME_SETS = {"threads": 1, "seed": 7, "val_instances": 8, "val_every": 10, "ckpt_every": 10, "sac.total_steps": 40,
               "sac.num_envs": 4, "sac.batch_size": 8, "sac.learning_starts": 16}


@pytest.fixture(scope="module")
def resume_data(tmp_path_factory):
    d = tmp_path_factory.mktemp("resume")
    return str(_lines(d / "train.h5", n=24, n_points=30, seed=1)), str(_lines(d / "val.h5", n=8, n_points=30, seed=2))


def _train_argv(data, out, *extra):
    argv = ["train", "--task", "line", "--data", data[0], "--val-data", data[1], "--out", out, "--device", "cpu",
            "--params", ""]
    for k, v in RESUME_SETS.items():
        argv += ["--set", f"{k}={v}"]
    return argv + list(extra)


def _weights(path, key):
    import torch

    ckpt = torch.load(path, weights_only=False)
    return ckpt[key], ckpt["step"]


def _same(a: dict, b: dict) -> bool:
    import torch

    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def reference(resume_data, tmp_path_factory):
    """The uninterrupted run: final agent (state file) and kept actor (checkpoint)."""
    d = tmp_path_factory.mktemp("reference")
    r = CliRunner().invoke(cli, _train_argv(resume_data, str(d / "m.pt"), "--no-tracking"))
    assert r.exit_code == 0, r.output
    agent, step = _weights(d / "m.state.pt", "agent")
    kept, kept_step = _weights(d / "m.pt", "actor")
    assert step == 40 and 0 < kept_step <= 40
    return {"agent": agent, "kept": kept, "kept_step": kept_step}


def _runs():
    import os

    import mlflow

    mlflow.set_tracking_uri(os.environ["MLFLOW_TRACKING_URI"])  # this test's store (the URI is process-global)
    return mlflow.search_runs(experiment_names=["lines"], output_format="list")


def _assert_resumed_exactly(workdir, reference):
    agent, step = _weights(workdir / "ck/m.state.pt", "agent")
    kept, kept_step = _weights(workdir / "ck/m.pt", "actor")
    assert step == 40
    assert _same(agent, reference["agent"])  # the same final model as the uninterrupted run
    assert kept_step == reference["kept_step"] and _same(kept, reference["kept"])  # and the same kept model


def test_sigterm_saves_state_ends_run_killed_and_resume_is_exact(workdir, resume_data, reference, monkeypatch):
    import os
    import signal

    from rlsac import train as train_mod

    real_loop = train_mod.train_loop
    sent = []

    def loop_with_sigterm(*args, log, **kw):
        def log_and_signal(metrics, step):
            if step >= 12 and not sent:  # at a fixed step: deterministic
                sent.append(step)
                os.kill(os.getpid(), signal.SIGTERM)
            return log(metrics, step)
        return real_loop(*args, log=log_and_signal, **kw)

    monkeypatch.setattr(train_mod, "train_loop", loop_with_sigterm)
    r = CliRunner().invoke(cli, _train_argv(resume_data, "ck/m.pt"))
    assert r.exit_code == 128 + signal.SIGTERM, r.output
    err = r.stderr.strip().splitlines()[-1]
    assert err.startswith("error: interrupted by SIGTERM at step ") and "continue with --resume" in err
    stopped_at, _ = _weights(workdir / "ck/m.state.pt", "agent")
    import torch

    step = torch.load(workdir / "ck/m.state.pt", weights_only=False)["step"]
    assert sent and sent[0] < step < 40  # stopped at the end of the running episode, state saved there
    runs = _runs()
    assert len(runs) == 1 and runs[0].info.status == "KILLED"
    assert "interrupted by SIGTERM" in runs[0].data.tags["error"] and runs[0].data.tags["command"] == "train"
    run_id = runs[0].info.run_id

    monkeypatch.setattr(train_mod, "train_loop", real_loop)
    r = CliRunner().invoke(cli, _train_argv(resume_data, "ck/m.pt", "--resume"))
    assert r.exit_code == 0, r.output
    _assert_resumed_exactly(workdir, reference)
    runs = _runs()
    assert [x.info.run_id for x in runs] == [run_id] and runs[0].info.status == "FINISHED"  # the same run, closed
    assert "error" not in runs[0].data.tags and "SIGTERM" in runs[0].data.tags["interrupted"]


def test_second_sigterm_stops_at_once_ends_run_killed_and_leaves_no_temporary_file(workdir, resume_data,
                                                                                     monkeypatch):
    """A first SIGTERM asks for a stop at the end of the episode; a second one, here while the state is being
    written, stops at once: the MLflow run ends KILLED (not RUNNING) and the save's temporary file is removed."""
    import signal

    import torch

    from rlsac import train as train_mod

    real_loop, real_save = train_mod.train_loop, torch.save
    before = signal.getsignal(signal.SIGTERM)
    sent = []

    def loop_with_sigterm(*args, log, **kw):
        def log_and_signal(metrics, step):
            if step >= 12 and not sent:
                sent.append(step)
                os.kill(os.getpid(), signal.SIGTERM)
            return log(metrics, step)
        return real_loop(*args, log=log_and_signal, **kw)

    def save(obj, f, *a, **k):
        real_save(obj, f, *a, **k)
        if sent and ".m.state.pt." in str(f):  # the state's temporary file, written and not yet renamed
            sent.append("second")
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(train_mod, "train_loop", loop_with_sigterm)
    monkeypatch.setattr(torch, "save", save)
    r = CliRunner().invoke(cli, _train_argv(resume_data, "ck/m.pt"))
    assert sent[-1] == "second"
    assert r.exit_code == 128 + signal.SIGTERM, (r.output, r.exception)
    err = r.stderr.strip().splitlines()[-1]
    assert err.startswith("error: interrupted by a second SIGTERM: stopped at once"), err
    assert not list((workdir / "ck").glob(".*.tmp"))  # the save's temporary file removed on the way out
    runs = _runs()
    assert len(runs) == 1 and runs[0].info.status == "KILLED"
    assert "second SIGTERM" in runs[0].data.tags["error"]
    assert signal.getsignal(signal.SIGTERM) == before  # the handlers are back


KILL_DURING_SAVE = """
import os, signal, sys
import torch
real_save, saves = torch.save, []
def save(obj, f, *a, **k):
    real_save(obj, f, *a, **k)
    if ".m.state.pt." in str(f):  # the state's temporary file: written, not yet renamed into place
        saves.append(f)
        if len(saves) == 2:
            os.kill(os.getpid(), signal.SIGKILL)
torch.save = save
from rlsac.cli import main
main(sys.argv[1:])
"""


def test_sigkill_during_a_save_then_resume_is_exact_and_closes_the_run(workdir, resume_data, reference):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", KILL_DURING_SAVE, *_train_argv(resume_data, "ck/m.pt")],
                       capture_output=True, text=True, cwd=workdir, env={**__import__("os").environ,
                                                                         "OMP_NUM_THREADS": "1"})
    assert r.returncode == -9, r.stderr[-2000:]
    stale = list((workdir / "ck").glob(".m.state.pt.*.tmp"))
    assert len(stale) == 1  # what a kill during a save leaves
    runs = _runs()
    assert len(runs) == 1 and runs[0].info.status == "RUNNING"
    run_id = runs[0].info.run_id
    # and a kill between the two writes of a save: an actor file from another step than the state's kept actor
    import torch

    torch.save({"actor": {}, "step": 30, "conf": {}}, workdir / "ck/m.pt")

    res = CliRunner().invoke(cli, _train_argv(resume_data, "ck/m.pt", "--resume"))
    assert res.exit_code == 0, res.output
    assert not list((workdir / "ck").glob(".*.tmp"))  # cleaned on the next start
    _assert_resumed_exactly(workdir, reference)
    runs = _runs()
    assert [x.info.run_id for x in runs] == [run_id] and runs[0].info.status == "FINISHED"


def test_failed_run_records_its_error(workdir):
    from rlsac.tracking import start_run

    with pytest.raises(RlsacError):
        with start_run("lines", "boom"):
            raise RlsacError("the reason")
    with pytest.raises(KeyboardInterrupt):
        with start_run("lines", "stopped"):
            raise KeyboardInterrupt
    runs = {r.info.run_name: r for r in _runs()}
    assert runs["boom"].info.status == "FAILED" and runs["boom"].data.tags["error"] == "the reason"
    assert runs["stopped"].info.status == "KILLED" and "KeyboardInterrupt" in runs["stopped"].data.tags["error"]


def test_run_names_and_command_tags(workdir):
    for out in ("a.h5", "b.h5"):
        r = CliRunner().invoke(cli, ["synth-lines", "--n-instances", "3", "--out", out, "--params", ""])
        assert r.exit_code == 0, r.output
    runs = _runs()
    assert len({r.info.run_name for r in runs}) == 2  # the output name tells the runs apart
    assert {r.data.tags["command"] for r in runs} == {"synth-lines"}


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_stop_on_signal_defers_the_first_signal_and_restores_the_handlers(signame):
    import signal

    from rlsac.errors import Interrupted
    from rlsac.train import _StopOnSignal

    sig = getattr(signal, signame)
    before = signal.getsignal(sig)
    stop = _StopOnSignal()
    with pytest.raises(Interrupted, match=f"second {signame}") as e:
        with stop:
            assert not stop()
            os.kill(os.getpid(), sig)  # handled: no KeyboardInterrupt, no exit
            assert stop() and stop.signum == sig
            os.kill(os.getpid(), sig)  # the second one stops at once, through the with-blocks (run KILLED)
            pytest.fail("the second signal did not stop")
    assert e.value.exit_code == 128 + sig and e.value.run_status == "KILLED"
    assert signal.getsignal(sig) == before
