"""The leave-one-building-out benchmark: fold partition, hold-out and pool selection, per-pair seeding, the
uniform control, the fold table on known errors, and `rlsac folds` end to end on two small real scenes."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.config import load_params
from rlsac.data import fundamental
from rlsac.data.scenes import ImportConf, import_scenes
from rlsac.data.tutorial import PrepareConf, prepare
from rlsac.errors import RlsacError
from rlsac.evaluation import results
from rlsac.evaluation.evaluate import evaluate, pair_seed
from rlsac.experiments import folds
from rlsac.maths.metrics import mAA
from rlsac.reports import folds as fold_table

ROOT = Path(__file__).resolve().parents[1]
STRECHA = Path(os.environ.get("RLSAC_STRECHA", ROOT / "data" / "strecha"))


# ------------------------------------------------------------------------------------------ protocol


@pytest.mark.parametrize("params", ["params.yaml", "experiments/quick/params.yaml"])
def test_every_test_building_is_tested_once_and_never_trained_on(params):
    p = folds.protocol(load_params(ROOT / params))
    every = {s for b in p["scenes"] for s in folds.scene_list(p["scenes"][b])}
    tested = []
    for fold in p["test"]:
        train, test = (set(folds.scene_list(x)) for x in folds.split_scenes(p, fold))
        assert test == set(folds.scene_list(p["scenes"][fold])) and not train & test
        assert train | test == every  # the other buildings are the training set
        tested += sorted(test)
    assert len(tested) == len(set(tested))
    if params == "params.yaml":  # the paper profile tests all six scenes, grouped into four buildings
        assert sorted(tested) == sorted(every) and len(every) == 6 and len(p["test"]) == 4


# a model of folds.pool_models: the scale study's recipe on every fold (params.yaml folds.train.rlsac-scale)
SCALE = {"models": ["rlsac", "rlsac-scale"], "pool_models": ["rlsac-scale"],
         "train": {"rlsac": {}, "rlsac-scale": {"sac": {"total_steps": 10000}, "selection": "last", "episodes": {
             "pool": "data/folds/pool/{fold}.h5", "points": 150, "swap": True}}}}


@pytest.mark.parametrize("change, message", [
    ({"scenes": {"a": "x,y", "b": "y"}, "test": ["a"]}, "two buildings"),
    ({"test": ["moon"]}, "folds.test"),
    ({"models": ["rlsac", "other"]}, "folds.models"),
    ({"methods": ["rlsac"]}, "not a baseline"),
    ({"pool": {"easy": 0}}, "folds.pool"),
    ({"val_fraction": 1.0}, "val_fraction"),
    ({"bogus": 1}, "unknown params key"),
    ({"points": [100], "points_models": ["rlsac-nosnn"]}, "folds.points_models"),
    ({"points": [100], "points_methods": ["magsac"], "methods": ["uniform"]}, "points_methods"),
    ({"points": [5]}, "folds.points"),
    ({"points": [100], "variant_regimes": ["easy"]}, "model_regime"),
    ({"seeds": [1], "seed_models": ["rlsac-nosnn"]}, "folds.seed_models"),
    ({"seeds": [0, 1], "seed_models": ["rlsac"]}, "the seed of model 'rlsac' itself"),
    ({"seeds": [1, 1], "seed_models": ["rlsac"]}, "distinct training seeds"),
    ({"select_models": ["rlsac"]}, "folds.select_models"),  # not a model of seed_models
    ({"select_models": ["rlsac"], "seed_models": ["rlsac"], "select_iterations": [7]}, "select_iterations"),
    ({"select_tie": 2.0}, "select_tie"),
    ({"select_iterations": "1000"}, "select_iterations"),
    # RLSAC at scale's kind of model (folds.pool_models): its recipe names the fold's pool with {fold}
    ({**SCALE, "train": {"rlsac": {}, "rlsac-scale": {"episodes": {"pool": "data/folds/pool/castle.h5"}}}},
     r"episodes.pool must name it with \{fold\}"),
    ({**SCALE, "train": {"rlsac": {}, "rlsac-scale": {}}}, r"episodes.pool must name it with \{fold\}"),
    ({**SCALE, "train": {"rlsac": {}, "rlsac-scale": {"episodes": {"pool": "data/{fold}.h5"}}}},
     "the fold's pool is data/folds/pool/"),
    ({**SCALE, "file_models": ["rlsac", "rlsac-scale"]}, r"both hold \['rlsac-scale'\]"),
    ({**SCALE, "file_models": []}, "folds.file_models .* must be folds.models without folds.pool_models"),
    ({**SCALE, "seed_models": ["rlsac"], "file_seed_models": ["rlsac"], "seeds": [1]}, "fold_train_pool_seed"),
    ({**SCALE, "pool_models": ["rlsac-other"]}, "folds.pool_models"),
    ({**SCALE, "train": {"rlsac": {"episodes": {"pool": "data/folds/pool/{fold}.h5"}},
                         "rlsac-scale": SCALE["train"]["rlsac-scale"]}}, "only a model of folds.pool_models"),
    ({**SCALE, "train": {"rlsac": {"out": "x/{regime}.pt"}, "rlsac-scale": SCALE["train"]["rlsac-scale"]}},
     r"unknown placeholder \{regime\}"),
    ({**SCALE, "pool": {"easy": 0, "hard": 100}}, "at least as many"),
    ({**SCALE, "regimes": ["easy", "pool"], "pool": {"easy": 0, "pool": 1000}}, "data/folds/pool"),
])
def test_protocol_rejects_inconsistent_folds(change, message):
    with pytest.raises(RlsacError, match=message):
        folds.protocol({"folds": change})


def test_pool_models_train_on_their_folds_pool_with_every_seed():
    """RLSAC at scale (folds.pool_models): {fold} of its recipe is the fold trained, for the model and each training
    seed; it is a row of every regime like rlsac; the other models are the file models (dvc.yaml's fold_train)."""
    p = folds.protocol({"folds": {**SCALE, "seeds": [1, 2], "seed_models": ["rlsac", "rlsac-scale"]}})
    assert p["file_models"] == ["rlsac"] and p["file_seed_models"] == ["rlsac"] and p["pool_models"] == ["rlsac-scale"]
    o = {"device": "cpu", "threads": 1}
    for fold in ("castle", "entry"):
        for model in ("rlsac-scale", "rlsac-scale-s2"):
            opts = folds.train_options(p, {}, "hard", fold, model, o)
            assert opts["episodes"] == {"pool": f"data/folds/pool/{fold}.h5", "points": 150, "swap": True}, model
            assert opts["data"] == f"data/folds/hard/{fold}/train.h5" and opts["selection"] == "last"
            assert opts["sac"]["total_steps"] == 10000 and opts["out"] == f"checkpoints/folds/hard/{fold}/{model}.pt"
        assert folds.pool_file(fold) == Path(f"data/folds/pool/{fold}.h5")
        assert "episodes" not in folds.train_options(p, {}, "hard", fold, "rlsac", o)
    assert folds.train_options(p, {}, "hard", "castle", "rlsac-scale-s2", o)["seed"] == 2
    assert p["train"]["rlsac-scale"]["episodes"]["pool"] == "data/folds/pool/{fold}.h5"  # the recipe itself unfilled
    for regime in ("easy", "hard"):
        rows = folds.rows(p, "castle", regime)
        assert rows["rlsac-scale-s1"]["checkpoint"] == Path("checkpoints/folds/hard/castle/rlsac-scale-s1.pt")
        assert rows["rlsac-scale"]["method"] == "rlsac"
    assert folds.fill_fold({"a": ["x/{fold}", 3], "b": "{fold}{fold}"}, "f") == {"a": ["x/f", 3], "b": "ff"}
    with pytest.raises(RlsacError, match=r"unknown placeholder \{seed\}"):
        folds.fill_fold({"a": {"b": "x/{seed}.h5"}}, "castle")
    # the pool stage: one per fold, of the model regime
    assert folds.check_options({"stage": "pool", "fold": "castle"}, p)["regime"] == "hard"
    with pytest.raises(RlsacError, match="leave --regime out"):
        folds.check_options({"stage": "pool", "regime": "easy", "fold": "castle"}, p)
    with pytest.raises(RlsacError, match="needs --regime"):
        folds.check_options({"stage": "tune", "fold": "castle"}, p)


@pytest.mark.parametrize("params", ["params.yaml", "experiments/quick/params.yaml"])
def test_profiles_train_rlsac_at_scale_on_the_folds_pool(params):
    """Both profiles: rlsac-scale is a pool model with every seed, outside the lists whose stages re-train with the
    fold's files only, and the paper profile's recipe is the scale study's (with oneDNN's kernels, issue #46)."""
    p = folds.protocol(load_params(ROOT / params))
    assert p["pool_models"] == ["rlsac-scale"] and "rlsac-scale" in p["models"] and "rlsac-scale" in p["seed_models"]
    for key in ("select_models", "lo_models", "fast", "ablation_models", "prob_models", "points_models"):
        assert "rlsac-scale" not in p[key], key
    recipe = p["train"]["rlsac-scale"]
    assert recipe["episodes"] == {"pool": "data/folds/pool/{fold}.h5", "points": 150, "swap": True}
    assert recipe["selection"] == "last"
    if params == "params.yaml":
        assert recipe["sac"]["total_steps"] == 10000  # the scale study's choice on validation (reports/scale.md)
        assert recipe["kernels"] == "onednn"  # what its 20 runs were trained with (Table 2's legend says so)
        assert p["pool"][p["model_regime"]] == 1000


def test_unknown_fold_and_regime_are_user_errors():
    p = folds.protocol({})
    with pytest.raises(RlsacError, match="unknown fold"):
        folds.check_options({"stage": "data", "regime": "easy", "fold": "moon"}, p)
    with pytest.raises(RlsacError, match="unknown regime"):
        folds.check_options({"stage": "data", "regime": "medium", "fold": "castle"}, p)


def test_n_study_rows_read_their_own_data_and_checkpoints():
    """Table 3 (c): <row>-n<N> runs on data/folds/<regime>-n<N> (its model trained there with the model's recipe),
    only in the variant regimes; --points only prepares data, and only an N of folds.points."""
    p = folds.protocol({"folds": {"points": [100, 300], "points_models": ["rlsac"], "points_methods": ["uniform"],
                                  "variant_regimes": ["hard"]}})
    hard, easy = folds.rows(p, "castle", "hard"), folds.rows(p, "castle", "easy")
    assert hard["rlsac-n300"]["points"] == 300 and hard["rlsac"]["points"] is None
    assert hard["rlsac-n300"]["checkpoint"] == Path("checkpoints/folds/hard/castle/rlsac-n300.pt")
    assert hard["uniform-n100"] == {**hard["uniform"], "points": 100}
    assert "rlsac-n100" not in easy and "uniform-n100" not in easy
    assert folds.derived_models(p) == {"rlsac-n100": {"recipe": "rlsac", "points": 100, "seed": None},
                                       "rlsac-n300": {"recipe": "rlsac", "points": 300, "seed": None}}
    assert folds.data_dir("hard", "castle", 100) == Path("data/folds/hard-n100/castle")
    assert folds.split_points("uniform-n100") == ("uniform", 100)
    assert folds.split_points("rlsac-nosnn") == ("rlsac-nosnn", None) and folds.split_points("rlsac") == ("rlsac", None)
    opts = folds.train_options(p, {}, "hard", "castle", "rlsac-n300", {"device": "cpu", "threads": 1})
    assert opts["data"] == "data/folds/hard-n300/castle/train.h5" and opts["out"].endswith("castle/rlsac-n300.pt")
    assert folds.check_options({"stage": "train", "regime": "hard", "fold": "castle", "model": "rlsac-n100"}, p)
    with pytest.raises(RlsacError, match="--points goes with --stage data"):
        folds.check_options({"stage": "tune", "regime": "hard", "fold": "castle", "points": 100}, p)
    with pytest.raises(RlsacError, match=r"folds.points \[100, 300\]"):
        folds.check_options({"stage": "data", "regime": "hard", "fold": "castle", "points": 200}, p)
    with pytest.raises(RlsacError, match="folds.variant_regimes"):
        folds.check_options({"stage": "data", "regime": "easy", "fold": "castle", "points": 100}, p)


# ------------------------------------------------------------------------------- data: two real scenes


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """fountain-P11 and entry-P10 imported once (1000 features: a few seconds)."""
    out = tmp_path_factory.mktemp("raw")
    import_scenes(ImportConf(src=str(STRECHA), out=str(out), scenes="fountain-P11,entry-P10", max_features=1000,
                             min_matches=30), track=False, progress=False)
    return out


def _prep(root, tmp_path, name, **kw):
    kw.setdefault("max_pairs_per_scene", 10)  # keeps the SIFT descriptor work of each prepare small
    conf = PrepareConf(root=str(root), split="all", n_points=40, out=str(tmp_path / f"{name}.h5"), **kw)
    conf.check()
    prepare(conf, track=False, progress=False)
    return fundamental.read(tmp_path / f"{name}.h5")[0]


def test_holdout_splits_are_disjoint_and_complete(imported, tmp_path):
    every = _prep(imported, tmp_path, "all", scenes="fountain-P11")
    tr = _prep(imported, tmp_path, "tr", scenes="fountain-P11", holdout="train", val_fraction=0.3)
    va = _prep(imported, tmp_path, "va", scenes="fountain-P11", holdout="val", val_fraction=0.3)
    assert set(tr["pair"]).isdisjoint(va["pair"]) and set(tr["pair"]) | set(va["pair"]) == set(every["pair"])
    assert 0 < len(va["pair"]) < len(tr["pair"])


def test_pool_draws_from_lower_ranked_matches_with_the_pairs_own_seed(imported, tmp_path):
    top = _prep(imported, tmp_path, "top", scenes="fountain-P11")
    pool = _prep(imported, tmp_path, "pool", scenes="fountain-P11", pool=400)
    ratio = lambda d: fundamental.gt_inliers(d, 2.0).sum(1) / d["mask"].sum(1)  # noqa: E731
    assert ratio(pool).mean() < ratio(top).mean() - 0.05  # lower-ranked matches: more outliers
    assert np.median(pool["features"][..., 4]) > np.median(top["features"][..., 4])  # higher SNN ratios
    # a pair's drawn subset does not depend on what else is in the file (scenes, order, hold-out)
    both = _prep(imported, tmp_path, "both", scenes="entry-P10,fountain-P11", pool=400)
    key = pool["pair"][3]
    i, j = 3, int(np.flatnonzero((both["pair"] == key) & (both["scene"] == "fountain-P11"))[0])
    np.testing.assert_array_equal(pool["coords"][i], both["coords"][j])


def test_pool_stage_prepares_the_folds_training_pairs_with_the_pool_size(imported, tmp_path, monkeypatch):
    """`rlsac folds --stage pool`: the fold's training pairs (the train holdout of the other buildings) with the model
    regime's pool size as points per pair, the matches the training file's points were drawn from; the scale study's
    pool (rlsac.experiments.scale.make_pool) is the same preparation. A pool model refuses to train without it."""
    from rlsac.experiments import scale

    monkeypatch.chdir(tmp_path)
    params = {"fundamental": {"raw": str(imported), "n_points": 40, "max_pairs_per_scene": 8},
              "folds": {**SCALE, "test": ["fountain"], "scenes": {"fountain": "fountain-P11", "entry": "entry-P10"},
                        "val_fraction": 0.3, "pool": {"easy": 0, "hard": 150}, "methods": ["uniform"],
                        "train": {"rlsac": {}, "rlsac-scale": {"episodes": {
                            "pool": "data/folds/pool/{fold}.h5", "points": 40, "swap": True}}}}}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    base = ["folds", "--fold", "fountain", "--device", "cpu", "--no-tracking"]
    r = CliRunner().invoke(cli, base + ["--stage", "data", "--regime", "hard"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, base + ["--stage", "train", "--regime", "hard", "--model", "rlsac-scale"])
    assert r.exit_code == 2 and "data/folds/pool/fountain.h5: no pool file" in r.output
    r = CliRunner().invoke(cli, base + ["--stage", "pool"])
    assert r.exit_code == 0, r.output
    assert "150 points each -> data/folds/pool/fountain.h5" in r.output
    pool, attrs = fundamental.read(tmp_path / "data/folds/pool/fountain.h5")
    train, _ = fundamental.read(tmp_path / "data/folds/hard/fountain/train.h5")
    assert pool["coords"].shape[1] == 150 and attrs["n_points"] == 150 and "entry-P10" in attrs["scenes"]
    assert list(pool["pair"]) == list(train["pair"])  # the training pairs, the same order
    p = folds.protocol(params)
    made = scale.make_pool(p, params, {"fold": "fountain", "pool": 150}, track=False)
    again, _ = fundamental.read(made["pool"])
    assert made["pool"] == "data/scale/fountain/pool.h5" and made["pairs"] == len(pool["pair"])
    for k in pool:
        np.testing.assert_array_equal(again[k], pool[k], err_msg=k)


def test_a_pairs_result_does_not_depend_on_the_other_pairs(imported, tmp_path):
    _prep(imported, tmp_path, "f", scenes="fountain-P11")
    _prep(imported, tmp_path, "ef", scenes="entry-P10,fountain-P11")
    runs = {}
    for name in ("f", "ef"):
        for method in ("ransac", "uniform", "magsac"):
            evaluate({"task": "fundamental", "method": method, "data": str(tmp_path / f"{name}.h5"), "iterations": 30,
                      "device": "cpu", "out_dir": str(tmp_path / "ev" / name / method)}, track=False)
            runs[name, method] = pd.read_csv(tmp_path / "ev" / name / method / "errors.csv")
    for method in ("ransac", "uniform", "magsac"):
        a = runs["f", method].set_index("pair")
        b = runs["ef", method][runs["ef", method]["scene"] == "fountain-P11"].set_index("pair")
        pd.testing.assert_frame_equal(a[["err_R", "err_t"]], b.loc[a.index, ["err_R", "err_t"]])
    # and the seed is the pair's: another seed gives other random streams
    assert pair_seed(0, "fountain-P11", "0001-0005") != pair_seed(1, "fountain-P11", "0001-0005")
    assert pair_seed(0, "fountain-P11", "0001-0005") != pair_seed(0, "entry-P10", "0001-0005")


def test_uniform_control_uses_the_rlsac_environment(imported, tmp_path):
    """actor=None: the environment's episodes and de-duplication with uniform sets; no set is used twice."""
    from rlsac.estimation.sampling import set_keys
    from rlsac.rl.rollout import rlsac_estimate
    from rlsac.tasks.fundamental import FundamentalTask

    d = _prep(imported, tmp_path, "u", scenes="fountain-P11")
    batch = fundamental.to_batch(d, [0, 1])
    out = rlsac_estimate(FundamentalTask(), batch, None, 45, generator=torch.Generator().manual_seed(0), record=True)
    assert out["hypotheses"].tolist() == [45, 45] and len(out["steps"]) == 15  # per pair: 3 episodes x psi=15
    keys = torch.stack([set_keys(s["minimal_set"], 40) for s in out["steps"]]).view(15, 2, 3)  # (t, B, E)
    for b in range(2):
        assert keys[:, b].unique().numel() == 45
    assert out["valid"].all()


def test_guided_control_draws_by_match_quality_in_the_same_environment(imported, tmp_path):
    """guide logits: the environment's de-duplication holds, and low-SNN matches are drawn far more often than
    high-SNN ones (a cold temperature all but restricts the sets to the best matches)."""
    from rlsac.estimation.sampling import set_keys
    from rlsac.rl.rollout import rlsac_estimate
    from rlsac.tasks.fundamental import FundamentalTask

    task = FundamentalTask()
    d = _prep(imported, tmp_path, "g", scenes="fountain-P11", pool=400)
    batch = fundamental.to_batch(d, [0, 1])
    snn = task.match_quality(batch)
    assert torch.equal(snn, batch["features"][..., 4])
    out = rlsac_estimate(task, batch, None, 45, generator=torch.Generator().manual_seed(0), record=True,
                         guide=-snn / 0.02)
    sets = torch.stack([s["minimal_set"] for s in out["steps"][1:]]).view(14, 2, 3, 8)  # (t, B, E, m)
    keys = torch.stack([set_keys(s["minimal_set"], 40) for s in out["steps"][1:]]).view(14, 2, 3)
    for b in range(2):
        assert keys[:, b].unique().numel() == 42  # no set twice within the instance
        drawn = torch.bincount(sets[:, b].flatten(), minlength=40).float()
        order = snn[b].argsort()
        # per match, the best quarter is drawn > 3x as often as the worse half (uniform sets: about 1x)
        assert drawn[order[:10]].mean() > 3 * drawn[order[-20:]].mean()
    with pytest.raises(RlsacError, match="guide"):
        rlsac_estimate(task, batch, None, 45, guide=snn[:1])
    # through evaluate: its own summary names the temperature
    evaluate({"task": "fundamental", "method": "guided", "data": str(tmp_path / "g.h5"), "iterations": 30,
              "device": "cpu", "out_dir": str(tmp_path / "ev_g")}, track=False)
    assert json.loads((tmp_path / "ev_g" / "summary.json").read_text())["guide_temperature"] == 0.1
    with pytest.raises(RlsacError, match="guided"):
        evaluate({"task": "line", "method": "guided", "data": str(tmp_path / "g.h5")}, track=False)


def test_prosac_receives_the_matches_best_first(imported, tmp_path, monkeypatch):
    import cv2

    from rlsac.estimation.baselines import opencv_estimate
    from rlsac.tasks.fundamental import FundamentalTask

    d = _prep(imported, tmp_path, "p", scenes="fountain-P11", pool=400)
    batch = fundamental.to_batch(d, [0])
    seen = {}
    real = cv2.findFundamentalMat

    def spy(p1, p2, *args):
        seen["p1"] = p1.copy()
        return real(p1, p2, *args)

    monkeypatch.setattr(cv2, "findFundamentalMat", spy)
    task = FundamentalTask()
    out = opencv_estimate(task, batch, "prosac", 100, seed=3, quality=task.match_quality(batch))
    valid = batch["mask"][0].numpy()
    coords, snn = batch["coords"][0].numpy()[valid], batch["features"][0, :, 4].numpy()[valid]
    np.testing.assert_array_equal(seen["p1"], coords[np.argsort(snn, kind="stable"), :2])
    assert out["valid"][0] and out["inliers"][0].sum() >= 8


# ------------------------------------------------------------------------------------ table, known values


def _write_errors(root: Path, regime: str, fold: str, method: str, it: int, err_R, err_t):
    d = root / "folds" / regime / fold / method / f"i{it}"
    d.mkdir(parents=True)
    n = len(err_R)
    pd.DataFrame({"instance": range(n), "scene": fold, "pair": [f"p{i}" for i in range(n)], "err_R": err_R,
                  "err_t": err_t}).to_csv(d / "errors.csv", index=False)


def test_fold_table_pools_pairs_and_pairs_methods(tmp_path):
    ev = tmp_path / "eval"
    # fold a: 2 pairs, fold b: 4 pairs; rlsac gets every pair within 0.5 deg, uniform misses half of them
    _write_errors(ev, "hard", "a", "rlsac", 100, [0.5, 0.5], [0.5, 0.5])
    _write_errors(ev, "hard", "b", "rlsac", 100, [0.5] * 4, [0.5] * 4)
    _write_errors(ev, "hard", "a", "uniform", 100, [0.5, 20.0], [0.5, 20.0])
    _write_errors(ev, "hard", "b", "uniform", 100, [0.5, 20.0, 0.5, 20.0], [5.5, 20.0, 5.5, 20.0])
    rec = tmp_path / "rec" / "hard"
    rec.mkdir(parents=True)
    (rec / "a.json").write_text(json.dumps({"splits": {"test": {
        "pairs": 2, "skipped": 0, "mean_gt_inlier_ratio_sampson_2px": 0.4, "gt_inlier_ratio_quantiles": {}}}}))
    got = fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    df = pd.read_csv(tmp_path / "out" / "table2_folds.csv")
    u = df[df["method"] == "uniform"].iloc[0]
    assert u["n"] == 6
    assert u["mAA_R"] == pytest.approx(mAA(np.array([0.5, 20, 0.5, 20, 0.5, 20]), 10.0)) == pytest.approx(0.5)
    assert u["mAA_t"] == pytest.approx((1 + 0 + 0.5 + 0 + 0.5 + 0) / 6, abs=1e-4)  # CSV keeps 4 decimals
    assert u["a R"] == pytest.approx(0.5) and u["b t"] == pytest.approx(0.25)
    assert u["dR"] == pytest.approx(-0.5) and u["dR_hi"] < 0  # paired against rlsac: uniform is worse
    md = (tmp_path / "out" / "table2_folds.md").read_text()
    assert "6 test pairs pooled over 2 folds" in md and "one pair moves a pooled mAA by 0.1667" in md
    assert "RLSAC − uniform" in md and "+0.500" in md
    it = pd.read_csv(tmp_path / "out" / "folds_iterations.csv")
    assert set(it["method"]) == {"rlsac", "uniform"} and (it["n_pairs"] == 6).all()
    assert got["files"] and not got["missing"]


def test_fold_table_sets_the_lo_model_against_the_lo_control(tmp_path):
    """Issue #26, like for like: RLSAC with LO is paired with uniform sets with the same LO (uniform-lo), never with
    the uniform control without LO. Here rlsac-lo has uniform-lo's rotation errors (one pair apart in t) and both are
    far above uniform: a zero R difference proves the pairing."""
    ev = tmp_path / "eval"
    _write_errors(ev, "hard", "a", "rlsac", 100, [0.5] * 4, [0.5] * 4)
    _write_errors(ev, "hard", "a", "uniform", 100, [20.0] * 4, [20.0] * 4)
    _write_errors(ev, "hard", "a", "rlsac-lo", 100, [0.5, 20.0, 0.5, 0.5], [0.5] * 4)
    _write_errors(ev, "hard", "a", "uniform-lo", 100, [0.5, 20.0, 0.5, 0.5], [0.5, 0.5, 0.5, 20.0])
    fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    md = (tmp_path / "out" / "table2_folds.md").read_text()
    section = md.split("### RLSAC − uniform", 1)[1].split("###", 1)[0]
    rows = {cells[1].strip(): cells for cells in (line.split("|") for line in section.splitlines()[4:] if line)}
    lo = next(cells for name, cells in rows.items() if "LO" in name)
    assert lo[2].strip() == fold_table.NAMES["uniform-lo"]  # the control named is the LO one
    assert lo[4].strip() == "+0.000 [+0.000, +0.000]" and lo[5].strip().startswith("+0.250")  # R equal, t: one pair
    plain = next(cells for name, cells in rows.items() if "LO" not in name)
    assert plain[2].strip() == fold_table.NAMES["uniform"]
    assert plain[4].strip().startswith("+1.000")  # RLSAC (no LO) against uniform (no LO): every pair


def test_fold_table_refuses_one_method_shown_as_two_rows(tmp_path):
    """Issue #26: Table E showed USAC_ACCURATE beside USAC although OpenCV's findEssentialMat ignores the flag (every
    error identical). Identical errors in every regime and budget are refused before anything is written; equal
    errors in one cell only are a legitimate tie."""
    ev = tmp_path / "eval"
    for fold, n in (("a", 2), ("b", 3)):
        for it in (100, 1000):
            _write_errors(ev, "hard", fold, "usac", it, [0.5 + it * 1e-3] * n, [2.0] * n)
            _write_errors(ev, "hard", fold, "usac_accurate", it, [0.5 + it * 1e-3] * n, [2.0] * n)
            _write_errors(ev, "hard", fold, "rlsac", it, [1.5] * n, [2.0] * n)
    with pytest.raises(RlsacError, match="'usac' and 'usac_accurate' give identical errors"):
        fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    assert not (tmp_path / "out").exists()
    import shutil

    shutil.rmtree(ev / "folds" / "hard" / "b" / "usac_accurate" / "i1000")
    _write_errors(ev, "hard", "b", "usac_accurate", 1000, [0.5, 0.7, 0.5], [2.0] * 3)  # differs in one cell
    assert fold_table.build(ev, tmp_path / "out", tmp_path / "rec")["files"]


def test_table3_sets_each_n_against_uniform_on_the_same_points_and_keeps_them_out_of_table2(tmp_path):
    """Table 3 (c): rlsac-n<N> and uniform-n<N> ran on other data (N points per pair): they are Table 3's rows, set
    against each other on the same pairs, and never rows of Table 2 (whose rows share the N = 150 data)."""
    ev = tmp_path / "eval"
    _write_errors(ev, "hard", "a", "rlsac", 100, [0.5] * 4, [0.5] * 4)
    _write_errors(ev, "hard", "a", "uniform", 100, [0.5] * 4, [20.0] * 4)
    _write_errors(ev, "hard", "a", "rlsac-nodesc", 100, [0.5, 0.5, 0.5, 0.6], [0.5] * 4)
    _write_errors(ev, "hard", "a", "rlsac-n100", 100, [0.5, 0.5, 20.0, 20.0], [0.5] * 4)
    _write_errors(ev, "hard", "a", "uniform-n100", 100, [20.0] * 4, [0.5, 0.5, 0.5, 20.0])
    fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    t2 = pd.read_csv(tmp_path / "out" / "table2_folds.csv")
    assert set(t2["method"]) == {"rlsac", "uniform", "rlsac-nodesc"}
    assert set(pd.read_csv(tmp_path / "out" / "folds_iterations.csv")["method"]) == {"rlsac", "uniform",
                                                                                    "rlsac-nodesc"}
    t3 = pd.read_csv(tmp_path / "out" / "table3_folds.csv")
    n100 = t3[t3["row"] == "rlsac-n100"].iloc[0]
    assert n100["mAA_R"] == pytest.approx(0.5) and n100["R − full"].startswith("-0.500")  # two pairs lost of four
    md = (tmp_path / "out" / "table3_folds.md").read_text()
    section = md.split("#### (c) against the uniform control", 1)[1]
    rows = {c[1].strip(): [x.strip() for x in c] for c in (line.split("|") for line in section.splitlines()[4:6])}
    assert rows["100"][2] == "rlsac-n100 / uniform-n100" and rows["100"][6].startswith("+0.500")  # R: 2 of 4 pairs
    assert rows["100"][7].startswith("+0.250")  # t: uniform-n100 loses one pair of four
    assert rows["150 (full)"][2] == "rlsac / uniform" and rows["150 (full)"][7].startswith("+1.000")


def test_other_training_seeds_train_with_the_models_recipe_and_their_seed():
    p = folds.protocol({"folds": {"seeds": [3, 7], "seed_models": ["rlsac"]}})
    assert folds.derived_models(p)["rlsac-s7"] == {"recipe": "rlsac", "points": None, "seed": 7}
    for regime in ("easy", "hard"):  # every regime, like the model itself
        row = folds.rows(p, "castle", regime)["rlsac-s3"]
        assert row["checkpoint"] == Path("checkpoints/folds/hard/castle/rlsac-s3.pt") and row["method"] == "rlsac"
    params = {"train": {"fundamental": {"seed": 0, "sac": {"total_steps": 5}}}}
    opts = folds.train_options(p, params, "hard", "castle", "rlsac-s7", {"device": "cpu", "threads": 1})
    assert opts["seed"] == 7 and opts["sac"]["total_steps"] == 5 and opts["out"].endswith("castle/rlsac-s7.pt")
    assert folds.train_options(p, params, "hard", "castle", "rlsac", {"device": "cpu", "threads": 1})["seed"] == 0
    assert folds.split_seed("rlsac-s12") == ("rlsac", 12) and folds.split_seed("rlsac-nosnn") == ("rlsac-nosnn", None)


def test_variant_rows_of_seeded_models_are_rows_per_seed():
    """Issue #27: with seed_ablation_models every variant row of a seeded model (-lo, -fast, -prob, the ablation
    models) is a row per seed in the variant regimes, on that seed's checkpoint; a variant of an unseeded model is
    refused, since its per-seed stages would have no model."""
    p = folds.protocol({"folds": {"models": ["rlsac"], "ablation_models": ["rlsac-trainmax"],
                                  "train": {"rlsac": {}, "rlsac-trainmax": {"sac": {"train_sampling": "max"}}},
                                  "seeds": [2], "seed_models": ["rlsac"], "seed_ablation_models": ["rlsac-trainmax"],
                                  "lo_models": ["rlsac"], "fast": ["rlsac"], "prob_models": ["rlsac-trainmax"],
                                  "variant_regimes": ["hard"]}})
    hard, easy = folds.rows(p, "castle", "hard"), folds.rows(p, "castle", "easy")
    ck = Path("checkpoints/folds/hard/castle")
    assert hard["rlsac-lo-s2"] == {**hard["rlsac-lo"], "checkpoint": ck / "rlsac-s2.pt"}
    assert hard["rlsac-fast-s2"]["fast"] and hard["rlsac-fast-s2"]["checkpoint"] == ck / "rlsac-s2.pt"
    assert hard["rlsac-trainmax-prob-s2"]["sampling"] == "prob"
    assert hard["rlsac-trainmax-prob-s2"]["checkpoint"] == ck / "rlsac-trainmax-s2.pt"
    assert hard["rlsac-trainmax-s2"]["checkpoint"] == ck / "rlsac-trainmax-s2.pt"
    assert not {"rlsac-lo-s2", "rlsac-trainmax-s2", "rlsac-fast-s2"} & set(easy) and "rlsac-s2" in easy
    assert folds.derived_models(p)["rlsac-trainmax-s2"] == {"recipe": "rlsac-trainmax", "points": None, "seed": 2}
    assert folds.split_seed("rlsac-trainmax-prob-s2") == ("rlsac-trainmax-prob", 2)
    with pytest.raises(RlsacError, match=r"folds.prob_models \['rlsac-trainmax'\]: with folds.seeds every one"):
        folds.protocol({"folds": {"models": ["rlsac"], "ablation_models": ["rlsac-trainmax"],
                                  "train": {"rlsac": {}, "rlsac-trainmax": {}}, "seeds": [2], "seed_models": ["rlsac"],
                                  "prob_models": ["rlsac-trainmax"]}})


def test_table3_and_the_lo_arm_take_their_variants_over_seeds(tmp_path):
    """Table 3's variants with seeds are set against the full model over its seeds in Table 3 (not against Table 2's
    controls), and a same-LO row with seeds against the same-LO rows only."""
    ev = tmp_path / "eval"
    for fold in ("a", "b"):
        _write_errors(ev, "hard", fold, "rlsac", 100, [0.5] * 4, [0.5] * 4)
        _write_errors(ev, "hard", fold, "rlsac-s1", 100, [0.5, 0.5, 20.0, 20.0], [0.5] * 4)
        _write_errors(ev, "hard", fold, "uniform", 100, [0.5, 20.0] * 2, [0.5, 20.0] * 2)
        _write_errors(ev, "hard", fold, "rlsac-nodesc", 100, [20.0] * 4, [0.5] * 4)
        _write_errors(ev, "hard", fold, "rlsac-nodesc-s1", 100, [20.0] * 4, [0.5, 0.5, 0.5, 0.6])
        _write_errors(ev, "hard", fold, "rlsac-lo", 100, [0.4] * 4, [0.5] * 4)
        _write_errors(ev, "hard", fold, "rlsac-lo-s1", 100, [0.4] * 4, [20.0] * 4)
        _write_errors(ev, "hard", fold, "uniform-lo", 100, [0.5] * 4, [0.5, 20.0] * 2)
    fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    t2 = (tmp_path / "out" / "table2_folds.md").read_text().split("### Across training seeds", 1)[1]
    t2 = t2.split("### Across training seeds, per test building", 1)[0]
    assert "rlsac-nodesc" not in t2 and fold_table.NAMES["rlsac-nodesc"] not in t2
    lo = [x for x in t2.splitlines() if fold_table.NAMES["rlsac-lo"] + " (2 seeds)" in x]
    assert [c.strip() for c in lo[0].split("|")[1:-1]][2] == fold_table.NAMES["uniform-lo"] and len(lo) == 1
    t3 = (tmp_path / "out" / "table3_folds.md").read_text().split("#### Across training seeds (100 iterations", 1)[1]
    line = next(x for x in t3.splitlines() if "rlsac-nodesc (2 seeds)" in x)
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[1:3] == ["rlsac-nodesc (2 seeds)", "rlsac (2 seeds)"]
    assert cells[3] == "0.000 ± 0.000" and cells[4].startswith("-0.750")  # R: none against the full seeds' 0.75
    assert cells[6] == "1.000 ± 0.000" and cells[7].startswith("+0.000")  # t: every pair within both


def test_table_e_rows_of_other_training_seeds_read_their_own_checkpoints():
    """Issue #27 on Table E: essential.seeds adds rows rlsac-s<seed>, each with the essential_train_seed stage's
    checkpoint; seed 0 is the model itself, so the list starts at 1."""
    p = folds.protocol({})
    e = folds.for_task(p, {"essential": {"seeds": [2]}}, "essential")
    rows = folds.rows(e, "castle", "hard")
    assert rows["rlsac"]["checkpoint"] == Path("checkpoints/essential/hard/castle.pt")
    assert rows["rlsac-s2"]["checkpoint"] == Path("checkpoints/essential/hard/castle-s2.pt")
    assert rows["rlsac-s2"]["method"] == "rlsac" and rows["rlsac-s2"]["knobs"] == ["refit_output"]
    assert "rlsac-s2" not in folds.rows(folds.for_task(p, {}, "essential"), "castle", "hard")
    with pytest.raises(RlsacError, match="essential.seeds"):
        folds.for_task(p, {"essential": {"seeds": [0]}}, "essential")


def test_fold_table_across_seeds_resamples_seeds_and_keeps_them_out_of_the_main_rows(tmp_path):
    """Two seeds of rlsac (one solves every pair, one none) against uniform (half): the seed mean ties the control
    and the interval spans the seeds' spread; rlsac-s1 is no row of Table 2's main tables or the iterations CSV."""
    ev = tmp_path / "eval"
    for fold in ("a", "b"):
        _write_errors(ev, "hard", fold, "rlsac", 100, [0.5] * 4, [0.5] * 4)
        _write_errors(ev, "hard", fold, "rlsac-s1", 100, [20.0] * 4, [20.0] * 4)
        _write_errors(ev, "hard", fold, "uniform", 100, [0.5, 20.0] * 2, [0.5, 20.0] * 2)
    fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    assert set(pd.read_csv(tmp_path / "out" / "table2_folds.csv")["method"]) == {"rlsac", "uniform"}
    assert set(pd.read_csv(tmp_path / "out" / "folds_iterations.csv")["method"]) == {"rlsac", "uniform"}
    md = (tmp_path / "out" / "table2_folds.md").read_text()
    section = md.split("### Across training seeds", 1)[1]
    line = next(x for x in section.splitlines() if "(2 seeds)" in x and fold_table.NAMES["uniform"] in x)
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[3] == "0.500 ± 0.707" and cells[4] == "0.500"  # R: seed mean and SD, the control's mAA
    lo, hi = (float(x) for x in cells[5].split("[")[1].rstrip("]").split(","))
    assert cells[5].startswith("+0.000") and lo <= -0.5 and hi >= 0.5 and cells[6] == "0.50"
    # a variant with seeds against the paper recipe: both sides over their seeds (rlsac's mean 0.5, SD 0.707)
    for fold in ("a", "b"):
        _write_errors(ev, "hard", fold, "rlsac-nosnn", 100, [0.6] * 4, [0.6] * 4)
        _write_errors(ev, "hard", fold, "rlsac-nosnn-s1", 100, [0.7] * 4, [0.7] * 4)
    fold_table.build(ev, tmp_path / "out2", tmp_path / "rec")
    md = (tmp_path / "out2" / "table2_folds.md").read_text().split("### Across training seeds", 1)[1]
    line = next(x for x in md.splitlines() if x.count("(2 seeds)") == 2)
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[3] == "1.000 ± 0.000" and cells[4] == "0.500 ± 0.707" and cells[5].startswith("+0.500")


def test_fold_table_across_seeds_per_test_building(tmp_path):
    """Issue #29: the across-seed comparison within each test building at the largest budget. Building a: both rlsac
    seeds solve every pair, uniform none (+1, whatever is resampled); building b: one seed solves all, the other none,
    uniform all (-0.5, the interval from -1 to 0 as the seeds are drawn). t: everyone solves building a's pairs."""
    ev = tmp_path / "eval"
    for it in (10, 100):
        far = 20.0 if it == 100 else 0.0  # at 10 iterations all rows tie: the section must show 100's
        _write_errors(ev, "hard", "a", "rlsac", it, [0.0] * 4, [0.0] * 4)
        _write_errors(ev, "hard", "a", "rlsac-s1", it, [0.0] * 4, [0.0] * 4)
        _write_errors(ev, "hard", "a", "uniform", it, [far] * 4, [0.0] * 4)
        _write_errors(ev, "hard", "b", "rlsac", it, [0.0] * 4, [0.0] * 4)
        _write_errors(ev, "hard", "b", "rlsac-s1", it, [far] * 4, [far] * 4)
        _write_errors(ev, "hard", "b", "uniform", it, [0.0] * 4, [0.0] * 4)
    fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    md = (tmp_path / "out" / "table2_folds.md").read_text()
    section = md.split("### Across training seeds, per test building (100 iterations)", 1)[1]
    assert "Pairs per building: a 4, b 4" in section
    head = next(x for x in section.splitlines() if x.startswith("| model"))
    line = next(x for x in section.splitlines() if fold_table.NAMES["uniform"] in x)
    cells = dict(zip([c.strip() for c in head.split("|")[1:-1]], [c.strip() for c in line.split("|")[1:-1]],
                     strict=True))
    assert cells["model"] == fold_table.NAMES["rlsac"] + " (2 seeds)"
    assert cells["a R"] == "+1.000 [+1.000, +1.000]" and cells["a t"] == "+0.000 [+0.000, +0.000]"
    assert cells["b R"] == "-0.500 [-1.000, +0.000]" and cells["b t"] == "-0.500 [-1.000, +0.000]"


def test_table_refuses_an_n_row_run_on_other_data(tmp_path):
    ev = tmp_path / "eval"
    _write_errors(ev, "hard", "a", "rlsac", 100, [0.5] * 2, [0.5] * 2)
    _write_errors(ev, "hard", "a", "uniform-n100", 100, [0.5, 20.0], [0.5] * 2)
    cell = ev / "folds/hard/a/uniform-n100/i100"
    (cell / "config.json").write_text(json.dumps({"method": "uniform", "iterations": 100, "checkpoint": None,
                                                  "data": "data/folds/hard/a/test.h5",
                                                  "data_attrs": {"n_points": 150}}))
    with pytest.raises(RlsacError, match="not on the data with 100 points"):
        fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    (cell / "config.json").write_text(json.dumps({"method": "uniform", "iterations": 100, "checkpoint": None,
                                                  "data": "data/folds/hard-n100/a/test.h5",
                                                  "data_attrs": {"n_points": 100}}))
    assert fold_table.build(ev, tmp_path / "out", tmp_path / "rec")["files"]


@pytest.mark.parametrize("row, ckpt, ok", [
    ("rlsac-s1", "checkpoints/essential/hard/fountain-s1.pt", True),  # Table E: the checkpoint's name is the fold's
    ("rlsac", "checkpoints/essential/hard/fountain.pt", True),
    ("rlsac", "checkpoints/essential/hard/fountain-s1.pt", False),  # another seed's model in the first seed's row
    ("rlsac", "checkpoints/folds/hard/fountain/rlsac-s1.pt", False),
    ("rlsac-lo", "checkpoints/folds/hard/fountain/rlsac.pt", True),
    ("rlsac-s2", "checkpoints/folds/hard/fountain/rlsac-s2.pt", True),
    ("rlsac", "scratch/mine.pt", True),  # a checkpoint outside the pipeline's layout: told by its method only
    ("rlsac-s1", "/abs/repo/checkpoints/essential/hard/fountain-s1.pt", True),
    # issue #27: a seeded model's variant rows are <row>-s<seed>, on that seed's checkpoint
    ("rlsac-lo-s2", "checkpoints/folds/hard/fountain/rlsac-s2.pt", True),
    ("rlsac-lo-s2", "checkpoints/folds/hard/fountain/rlsac-s3.pt", False),
    ("rlsac-lo-s2", "checkpoints/folds/hard/fountain/rlsac.pt", False),
    ("rlsac-fast-s2", "checkpoints/folds/hard/fountain/rlsac-s2.pt", True),
    ("rlsac-trainmax-prob-s1", "checkpoints/folds/hard/fountain/rlsac-trainmax-s1.pt", True),
    ("rlsac-trainmax-prob-s1", "checkpoints/folds/hard/fountain/rlsac-trainmax.pt", False),
])
def test_a_models_cell_must_hold_the_checkpoint_its_folder_names(tmp_path, row, ckpt, ok):
    cell = tmp_path / row / "i100"
    cell.mkdir(parents=True)
    method = "rlsac-lo" if "-lo" in row else "rlsac"
    sampling = "prob" if "-prob" in row else "max"
    (cell / "config.json").write_text(json.dumps({"method": method, "iterations": 100, "checkpoint": ckpt,
                                                  "sampling": sampling}))
    from rlsac.tasks.essential import EssentialTask

    essential = folds.checkpoint("hard", "fountain", "rlsac-s3", EssentialTask.fold_checkpoint)
    assert essential == Path("checkpoints/essential/hard/fountain-s3.pt")
    assert folds.checkpoint_model(essential) == "rlsac-s3"
    assert folds.checkpoint("hard", "fountain", "rlsac", EssentialTask.fold_checkpoint) == Path(
        "checkpoints/essential/hard/fountain.pt")
    assert folds.checkpoint_model(folds.checkpoint("hard", "fountain", "rlsac-nosnn")) == "rlsac-nosnn"
    assert folds.checkpoint_model("scratch/ess.pt") is None
    if ok:
        results._check_cell(cell, row, 100)
    else:
        with pytest.raises(RlsacError, match="its folder names"):
            results._check_cell(cell, row, 100)


def test_fold_table_shows_rlsac_at_scale_absent_then_with_its_seeds(tmp_path):
    """Table 2's row "RLSAC at scale" (rlsac-scale) with its legend line: "–" in every cell while its results are
    absent (no CSV row: the CSVs hold results), then its numbers, its paired difference to rlsac, its controls and
    its across-seed comparisons like rlsac's once its seeds' results exist."""
    label = fold_table.NAMES["rlsac-scale"]
    assert label == "RLSAC at scale"
    ev = tmp_path / "eval"
    for fold in ("a", "b"):
        _write_errors(ev, "hard", fold, "rlsac", 100, [0.5] * 4, [0.5] * 4)
        _write_errors(ev, "hard", fold, "rlsac-s1", 100, [0.5, 20.0] * 2, [0.5] * 4)
        _write_errors(ev, "hard", fold, "uniform", 100, [0.5, 20.0] * 2, [0.5, 20.0] * 2)
    fold_table.build(ev, tmp_path / "out", tmp_path / "rec")
    md = (tmp_path / "out" / "table2_folds.md").read_text()
    assert ("RLSAC at scale (`rlsac-scale`, not in the paper; five training seeds like RLSAC): the scale study's "
            "recipe: 10000 steps (33x), episodes redrawn from each pair's 1000 lowest-SNN matches with the images "
            "swapped, last actor, oneDNN kernels (`kernels: onednn`: the same losses as the study's, other last "
            "bits); reports/scale.md.") in md
    line = next(x for x in md.split("### 100 iterations", 1)[1].splitlines() if x.startswith(f"| {label} "))
    assert set(c.strip() for c in line.split("|")[2:-1]) == {"no LO", "–"}
    assert "rlsac-scale" not in set(pd.read_csv(tmp_path / "out" / "table2_folds.csv")["method"])
    assert "rlsac-scale" not in set(pd.read_csv(tmp_path / "out" / "folds_iterations.csv")["method"])
    assert label not in md.split("### Across training seeds", 1)[1]
    # no such row where it is not expected (Table E's default)
    fold_table.build(ev, tmp_path / "outE", tmp_path / "rec", sub="folds", stem="t", expected=())
    assert f"| {label} " not in (tmp_path / "outE" / "t.md").read_text()
    # its results: the row, its difference to rlsac, its controls, and its seeds against rlsac's and the controls'
    for fold in ("a", "b"):
        _write_errors(ev, "hard", fold, "rlsac-scale", 100, [0.5] * 4, [20.0, 0.5] * 2)
        _write_errors(ev, "hard", fold, "rlsac-scale-s1", 100, [0.5] * 4, [0.5, 0.5, 0.5, 5.5])
    fold_table.build(ev, tmp_path / "out2", tmp_path / "rec")
    md = (tmp_path / "out2" / "table2_folds.md").read_text()
    line = next(x for x in md.split("### 100 iterations", 1)[1].splitlines() if x.startswith(f"| {label} "))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[3:5] == ["1.000", "0.500"] and cells[-2].startswith("+0.000") and cells[-1].startswith("-0.500")
    assert "rlsac-scale" in set(pd.read_csv(tmp_path / "out2" / "table2_folds.csv")["method"])
    control = md.split("### RLSAC − uniform", 1)[1].split("###", 1)[0]
    assert f"| {label} " in control
    seeds = md.split("### Across training seeds", 1)[1].split("### Across training seeds, per test building", 1)[0]
    vs = {c.strip(): [x.strip() for x in line.split("|")[1:-1]] for line in seeds.splitlines()
          if line.startswith("|") and f"{label} (2 seeds)" in line for c in [line.split("|")[3]]}
    assert fold_table.NAMES["rlsac"] + " (2 seeds)" in vs and fold_table.NAMES["uniform"] in vs
    assert vs[fold_table.NAMES["rlsac"] + " (2 seeds)"][3] == "1.000 ± 0.000"  # both seeds of rlsac-scale: every pair


def test_fold_table_without_results_writes_nothing(tmp_path):
    got = fold_table.build(tmp_path / "none", tmp_path / "out", tmp_path / "rec")
    assert got["files"] == [] and not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------ end to end


def test_folds_command_end_to_end(imported, tmp_path, monkeypatch):
    """data -> train (both models) -> evaluate -> table for one tiny fold, through the CLI."""
    monkeypatch.chdir(tmp_path)
    params = {
        "fundamental": {"raw": str(imported), "n_points": 40, "max_pairs_per_scene": 8},
        "train": {"fundamental": {"threads": 1, "val_instances": 2, "val_iterations": 15, "val_every": 4,
                                  "ckpt_every": 4, "policy": {"graph_dims": 4},
                                  "sac": {"total_steps": 8, "num_envs": 2, "batch_size": 4, "learning_starts": 4}}},
        "folds": {"test": ["fountain"], "scenes": {"fountain": "fountain-P11", "entry": "entry-P10"},
                  "val_fraction": 0.3, "regimes": ["hard"], "pool": {"hard": 100},
                  "methods": ["uniform", "ransac"], "models": ["rlsac", "rlsac-ws"], "lo_models": ["rlsac-ws"],
                  "lo_methods": ["ransac-lo", "guided-lo"], "ablation_models": ["rlsac-trainmax"],
                  "prob_models": ["rlsac"],
                  "train": {"rlsac": {}, "rlsac-ws": {"sac": {"warm_start_updates": 2}, "selection": "val_mAA"},
                            "rlsac-trainmax": {"sac": {"train_sampling": "max"}}},
                  "iterations": [15], "seed": 0, "fast": ["rlsac"],
                  "points": [30], "points_models": ["rlsac"], "points_methods": ["uniform"],
                  "seeds": [1], "seed_models": ["rlsac", "rlsac-ws"], "select_models": ["rlsac"],
                  "select_iterations": [15]},
        "essential": {"regime": "hard", "methods": ["ransac", "usac"], "iterations": [15]},
        "tuning": {"iterations": 15, "threshold_px": [1.0, 2.0], "prefilter": [0.9, 1.0], "extend": 0,
                   "guide_temperature": [0.1], "lo_sigma_scale": [0.5], "sets_per_step": [2], "confidence": [0.99]},
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    run = CliRunner()
    base = ["folds", "--regime", "hard", "--fold", "fountain", "--device", "cpu", "--no-tracking"]
    r = run.invoke(cli, base + ["--stage", "evaluate"])
    assert r.exit_code == 2 and "run `rlsac folds --stage data` first" in r.output
    r = run.invoke(cli, base + ["--stage", "data"])
    assert r.exit_code == 0, r.output
    rec = json.loads((tmp_path / "reports/folds/data/hard/fountain.json").read_text())
    assert rec["test_scenes"] == "fountain-P11" and rec["train_scenes"] == "entry-P10"
    assert rec["splits"]["train"]["pairs"] + rec["splits"]["val"]["pairs"] == 8
    assert "n_points" not in rec  # the default regime's record keeps the committed record's bytes (dvc.lock)
    # Table 3 (c): the same fold with 30 points per pair, its own folder
    r = run.invoke(cli, base + ["--stage", "tune", "--only", "uniform-n30"])
    assert r.exit_code == 2 and "data/folds/hard-n30/fountain/val.h5: no such file" in r.output
    r = run.invoke(cli, base + ["--stage", "data", "--points", "30"])
    assert r.exit_code == 0, r.output
    rec30 = json.loads((tmp_path / "reports/folds/data/hard-n30/fountain.json").read_text())
    assert rec30["n_points"] == 30 and rec30["splits"]["test"]["pairs"] == rec["splits"]["test"]["pairs"]
    assert fundamental.read(tmp_path / "data/folds/hard-n30/fountain/test.h5")[0]["coords"].shape[1] == 30
    # evaluation needs the row's tuning record, made on the fold's validation pairs only
    r = run.invoke(cli, base + ["--stage", "evaluate", "--only", "uniform"])
    assert r.exit_code == 2 and "no tuning record" in r.output
    val, test = tmp_path / "data/folds/hard/fountain/val.h5", tmp_path / "data/folds/hard/fountain/test.h5"
    kept = val.read_bytes()
    val.write_bytes(test.read_bytes())  # the test pairs offered as validation pairs
    r = run.invoke(cli, base + ["--stage", "tune", "--only", "uniform"])
    assert r.exit_code == 2 and "test scene(s) ['fountain-P11']" in r.output
    assert not (tmp_path / "reports/tuning").exists()
    val.write_bytes(kept)
    r = run.invoke(cli, base + ["--stage", "tune", "--only", "uniform"])
    assert r.exit_code == 0, r.output
    record_path = tmp_path / "reports/tuning/fundamental/hard/fountain/uniform.json"
    record = json.loads(record_path.read_text())
    assert record["val_scenes"] == ["entry-P10"] and record["data"].endswith("val.h5")
    # coordinate search: the 2 thresholds at pre-filter 0.9, then pre-filter 1.0 at the better one
    assert len(record["grid"]) == 3 and record["chosen"]["threshold_px"] in (1.0, 2.0)
    good = record_path.read_text()
    record_path.write_text(json.dumps({**record, "val_scenes": ["entry-P10", "fountain-P11"]}))  # pooled val pairs
    r = run.invoke(cli, base + ["--stage", "evaluate", "--only", "uniform"])
    assert r.exit_code == 2 and "test scene(s) ['fountain-P11']" in r.output
    record_path.write_text(good)
    # baselines can run before any model is trained; a model needs its checkpoint
    r = run.invoke(cli, base + ["--stage", "evaluate", "--only", "uniform"])
    assert r.exit_code == 0, r.output
    conf = json.loads((tmp_path / "reports/eval/folds/hard/fountain/uniform/i15/config.json").read_text())
    assert conf["threshold_px"] == record["chosen"]["threshold_px"] and conf["sets_per_step"] == 1
    assert (tmp_path / "reports/eval/folds/hard/fountain/uniform/i15/summary.json").is_file()
    assert not (tmp_path / "reports/eval/folds/hard/fountain/ransac").exists()
    r = run.invoke(cli, base + ["--stage", "evaluate", "--only", "rlsac"])
    assert r.exit_code == 2 and "no checkpoint" in r.output
    r = run.invoke(cli, base + ["--stage", "train"])
    assert r.exit_code == 0, r.output
    ws = torch.load(tmp_path / "checkpoints/folds/hard/fountain/rlsac-ws.pt", weights_only=False)
    paper = torch.load(tmp_path / "checkpoints/folds/hard/fountain/rlsac.pt", weights_only=False)
    assert ws["selection"] == "val_mAA" and ws["conf"]["sac"]["warm_start_updates"] == 2
    assert paper["selection"] == "inlier_ratio" and paper["conf"]["sac"]["warm_start_updates"] == 0
    assert [h["step"] for h in paper["history"]][:2] == [4, 8]
    s1 = torch.load(tmp_path / "checkpoints/folds/hard/fountain/rlsac-s1.pt", weights_only=False)
    assert s1["conf"]["seed"] == 1 and paper["conf"]["seed"] == 0  # the paper recipe with another training seed
    assert not torch.equal(s1["actor"][next(iter(s1["actor"]))], paper["actor"][next(iter(paper["actor"]))])
    n30 = torch.load(tmp_path / "checkpoints/folds/hard/fountain/rlsac-n30.pt", weights_only=False)
    assert n30["conf"]["data"] == "data/folds/hard-n30/fountain/train.h5"  # the full recipe on the N = 30 data
    r = run.invoke(cli, base + ["--stage", "tune"])
    assert r.exit_code == 0, r.output
    fast = json.loads((tmp_path / "reports/tuning/fundamental/hard/fountain/rlsac-fast.json").read_text())
    assert {"sets_per_step", "confidence"} <= set(fast["chosen"])
    r = run.invoke(cli, base + ["--stage", "evaluate"])
    assert r.exit_code == 0, r.output
    guided_lo = json.loads((tmp_path / "reports/tuning/fundamental/hard/fountain/guided-lo.json").read_text())
    assert {"guide_temperature", "lo_sigma_scale"} <= set(guided_lo["chosen"])  # the sampler's knob and LO's
    trainmax = torch.load(tmp_path / "checkpoints/folds/hard/fountain/rlsac-trainmax.pt", weights_only=False)
    assert trainmax["conf"]["sac"]["train_sampling"] == "max"  # Table 3 (b)'s model, trained with the others
    prob = json.loads((tmp_path / "reports/eval/folds/hard/fountain/rlsac-prob/i15/config.json").read_text())
    assert prob["sampling"] == "prob" and prob["checkpoint"].endswith("rlsac.pt")
    for m in ("uniform-n30", "rlsac-n30"):  # tuned on the N = 30 validation pairs, tested on the N = 30 test pairs
        tuned = json.loads((tmp_path / f"reports/tuning/fundamental/hard/fountain/{m}.json").read_text())
        conf = json.loads((tmp_path / f"reports/eval/folds/hard/fountain/{m}/i15/config.json").read_text())
        assert tuned["data"] == "data/folds/hard-n30/fountain/val.h5" and conf["data_attrs"]["n_points"] == 30
    for m in ("uniform", "ransac", "rlsac", "rlsac-ws", "rlsac-ws-lo", "rlsac-fast", "ransac-lo", "guided-lo",
              "rlsac-trainmax", "rlsac-prob", "rlsac-n30", "uniform-n30", "rlsac-s1",
              "rlsac-ws-lo-s1", "rlsac-fast-s1", "rlsac-prob-s1"):  # issue #27: the variant rows per seed too
        s = json.loads((tmp_path / f"reports/eval/folds/hard/fountain/{m}/i15/summary.json").read_text())
        assert s["n_instances"] == 8 and s["iterations"] == 15
        assert ("lo" in s) == ("-lo" in m)
    r = run.invoke(cli, ["table", "--which", "folds", "--no-tracking"])
    assert r.exit_code == 0, r.output
    # metrics.json takes the pooled numbers from folds_iterations.csv, written earlier in the same all-or-nothing set
    pooled = json.loads((tmp_path / "reports/metrics.json").read_text())["folds"]["hard"]
    assert set(pooled["rlsac"]) == {"i15"} and 0 <= pooled["rlsac"]["i15"]["mAA_R"] <= 1
    md = (tmp_path / "reports/table2_folds.md").read_text()
    assert "8 test pairs pooled over 1 folds" in md and "| same LO " in md
    t3 = (tmp_path / "reports/table3_folds.md").read_text()  # Table 3 on the folds, each variant against the full model
    assert "Ours (max sampling in training, max in testing)" in t3 and "rlsac-trainmax" in t3 and "rlsac-prob" in t3
    assert re.search(r"\| 30 +\| rlsac-n30 / uniform-n30 ", t3) and "rlsac-n30" not in md  # (c): Table 3 only
    assert "### Across training seeds" in md and "(2 seeds)" in md
    assert "Settings chosen on each fold's validation pairs" in md and ("SNN<0.9" in md or "no filter" in md)
    errors = pd.read_csv(tmp_path / "reports/eval/folds/hard/fountain/uniform/i15/errors.csv")
    assert (errors["n_hypotheses"] == 15).all()  # the paper's algorithm: the whole budget, every pair
    # issue #27, item 3: the training replayed, every validated actor tested; the kept one's errors are its evaluation's
    r = run.invoke(cli, base + ["--stage", "select", "--model", "rlsac-ws"])
    assert r.exit_code == 2 and "needs --model, one of rlsac, rlsac-s1" in r.output
    r = run.invoke(cli, base + ["--stage", "select", "--model", "rlsac-s1"])
    assert r.exit_code == 0, r.output
    sel = json.loads((tmp_path / "reports/selection/hard/fountain/rlsac-s1.json").read_text())
    assert sel["steps"] == [4, 8] and sel["last_step"] == 8 and sel["kept_step"] == s1["step"] and sel["reproduced"]
    assert sel["kept_step"] in sel["candidates"] and [h["step"] for h in sel["history"]] == [4, 8]
    per_pair = pd.read_csv(tmp_path / "reports/selection/hard/fountain/rlsac-s1.csv", dtype={"pair": str})
    kept_rows = per_pair[per_pair["step"] == sel["kept_step"]]
    ev_s1 = pd.read_csv(tmp_path / "reports/eval/folds/hard/fountain/rlsac-s1/i15/errors.csv")
    assert len(per_pair) == 2 * 8 and np.allclose(kept_rows["err_R"], ev_s1["err_R"])
    other = per_pair[per_pair["step"] != sel["kept_step"]]
    assert mAA(other["err_R"].to_numpy(), 10) == pytest.approx(sel["test"][str(other["step"].iloc[0])]["15"]["mAA_R"])
    r = run.invoke(cli, ["table", "--which", "selection", "--no-tracking"])
    assert r.exit_code == 0, r.output
    assert "| rlsac   | 15 " in (tmp_path / "reports/selection.md").read_text()
    assert len(pd.read_csv(tmp_path / "reports/selection.csv")) == 2  # rlsac-s1's two validated actors
    ck = tmp_path / "checkpoints/folds/hard/fountain/rlsac-s1.pt"
    good_ck = ck.read_bytes()
    torch.save({**s1, "actor": {k: v + 1e-3 for k, v in s1["actor"].items()}}, ck)  # not what the options train
    r = run.invoke(cli, base + ["--stage", "select", "--model", "rlsac-s1"])
    assert r.exit_code == 2 and "does not give the kept actor" in r.output
    ck.write_bytes(good_ck)
    # Table E through the same protocol: our RANSAC also tunes the final refit, OpenCV's rows do not
    ess = base + ["--task", "essential"]
    r = run.invoke(cli, ess + ["--stage", "train"])
    assert r.exit_code == 2 and "essential" in r.output
    r = run.invoke(cli, ess + ["--stage", "select", "--model", "rlsac-s1"])  # not "needs --model, one of none"
    assert r.exit_code == 2 and "--task essential has tune and evaluate only" in r.output
    r = run.invoke(cli, ess + ["--stage", "tune"])
    assert r.exit_code == 2 and "no checkpoint checkpoints/essential/hard/fountain.pt" in r.output
    r = run.invoke(cli, ess + ["--stage", "tune", "--only", "ransac,usac"])
    assert r.exit_code == 0, r.output
    rec = json.loads((tmp_path / "reports/tuning/essential/hard/fountain/ransac.json").read_text())
    assert rec["task"] == "essential" and "refit_output" in rec["chosen"]
    usac = json.loads((tmp_path / "reports/tuning/essential/hard/fountain/usac.json").read_text())
    assert set(usac["chosen"]) == {"threshold_px", "prefilter"}
    r = run.invoke(cli, ess + ["--stage", "evaluate", "--only", "ransac,usac"])
    assert r.exit_code == 0, r.output
    conf = json.loads((tmp_path / "reports/eval/essential/hard/fountain/ransac/i15/config.json").read_text())
    assert conf["task"] == "essential" and conf["refit_output"] == rec["chosen"]["refit_output"]
    usac_err = pd.read_csv(tmp_path / "reports/eval/essential/hard/fountain/usac/i15/errors.csv")
    assert (usac_err["n_hypotheses"] <= 15).all()  # OpenCV: its stopping rule's bound, capped at the budget


def test_a_fold_model_stopped_part_way_resumes_its_own_state(tmp_path, monkeypatch):
    """rlsac folds --stage train: a state of this recipe short of its steps (a SIGTERM at a session's end) is resumed;
    a finished state, another recipe's or none trains from the start (issue #46: the 10k-step fold models)."""
    import torch

    import rlsac.data.fundamental as fundamental
    import rlsac.evaluation.train as train_mod
    import rlsac.experiments.folds as folds
    from rlsac.config import build

    for split in ("train", "val"):
        (tmp_path / f"{split}.h5").write_text("")
    opts = {"task": "line", "data": "x.h5", "out": str(tmp_path / "m.pt"), "seed": 0, "sac": {"total_steps": 30}}
    monkeypatch.setattr(folds, "data_dir", lambda *a: tmp_path)
    monkeypatch.setattr(fundamental, "read", lambda path: None)
    monkeypatch.setattr(folds, "train_options", lambda *a: dict(opts))
    calls = []
    monkeypatch.setattr(train_mod, "train", lambda o, track=True: calls.append(bool(o.get("resume"))) or {})
    conf = train_mod.stored_conf(build(train_mod.TrainConf, opts, "train"))
    p = {"models": ["m"]}
    for step, state_conf, want in ((None, None, False), (10, conf, True), (30, conf, False),
                                   (10, {**conf, "seed": 1}, False)):
        if step is not None:
            torch.save({"step": step, "conf": state_conf}, tmp_path / "m.state.pt")
        folds.train_models(p, {}, "hard", "castle", ["m"], {}, track=False)
        assert calls.pop() is want, (step, want)


def test_a_pool_recipe_may_wait_outside_the_lists_until_its_runs_are_recorded():
    """A pool model trained across sessions: its recipe is defined (rlsac folds --params with it listed trains it)
    while params.yaml's lists leave it out, so dvc.yaml has none of its stages yet; listed as a file model, refused."""
    staged = {**SCALE, "models": ["rlsac"], "pool_models": []}
    p = folds.protocol({"folds": staged})
    assert p["pool_models"] == [] and p["file_models"] == ["rlsac"]
    with pytest.raises(RlsacError, match="only a model of folds.pool_models"):
        folds.protocol({"folds": {**staged, "models": ["rlsac", "rlsac-scale"]}})


def test_the_train_summary_says_which_actor_was_kept():
    """A run kept by a rule names its score and step; a run that keeps the last actor (RLSAC at scale) has no score
    to report and says so, instead of a sentinel score at step None."""
    s = {"stage": "train", "regime": "hard", "fold": "castle", "seconds": 1.0, "models": {
        "rlsac": {"checkpoint": "a.pt", "selection": "inlier_ratio", "best_score": 0.4251, "best_step": 200,
                  "steps": 300},
        "rlsac-scale": {"checkpoint": "b.pt", "selection": "last", "best_score": -1.0, "best_step": None,
                        "steps": 10000}}}
    assert folds.format_summary(s) == ("folds train hard/castle (1.0 s): rlsac -> a.pt (best inlier_ratio 0.425 at "
                                       "step 200); rlsac-scale -> b.pt (the last actor, step 10000)")


def test_the_tasks_part_in_the_fold_benchmark_is_the_tasks_not_a_branch_on_its_name():
    """Issue #65 item 3: Table E's rows, stages, checkpoints and knobs come from EssentialTask's attributes (for_task
    puts them into the protocol), the fundamental benchmark's from FundamentalTask's; the line task has none."""
    from rlsac.tasks.essential import EssentialTask

    params = {"essential": {"seeds": [2]}}
    p = folds.for_task(folds.protocol({}), params, "essential")
    assert p["fold_stages"] == ["tune", "evaluate"] and p["sampler_knobs"] == ["refit_output"]
    table = folds.rows(p, "fountain")
    assert table["rlsac"]["checkpoint"] == Path("checkpoints/essential") / p["model_regime"] / "fountain.pt"
    assert table["rlsac-s2"]["checkpoint"] == Path("checkpoints/essential") / p["model_regime"] / "fountain-s2.pt"
    assert "refit_output" in table["rlsac"]["knobs"]
    assert all("refit_output" not in r["knobs"] for r in table.values() if r["method"] not in folds.OUR_SAMPLERS)
    f = folds.for_task(folds.protocol({}), params, "fundamental")
    assert "refit_output" not in folds.rows(f, "fountain")["rlsac"]["knobs"]
    assert folds.rows(f, "fountain")["rlsac"]["checkpoint"] == Path("checkpoints/folds") / f["model_regime"] / \
        "fountain/rlsac.pt"
    with pytest.raises(RlsacError, match="folds --task must be fundamental or essential, got 'line'"):
        folds.for_task(folds.protocol({}), params, "line")
    try:  # a task whose fold stages leave out `retune` is refused there, whatever its name
        EssentialTask.fold_stages = ("tune",)
        with pytest.raises(RlsacError, match="--stage evaluate: --task essential has tune only"):
            folds.check_options({"stage": "evaluate", "task": "essential", "fold": "fountain", "regime": "hard"},
                                folds.for_task(folds.protocol({}), params, "essential"))
    finally:
        EssentialTask.fold_stages = ("tune", "evaluate")
