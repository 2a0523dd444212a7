"""Report tables (paper beside ours), the iterations CSV, figures and ``rlsac table`` on fake result trees."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd
import pytest
import torch
from click.testing import CliRunner

from rlsac import config
from rlsac.cli import cli
from rlsac.data import lines
from rlsac.evaluation.train import TrainConf
from rlsac.reports import figures, paper, tables
from rlsac.rl.policy import Actor, PolicyConf
from rlsac.rl.rollout import in_channels
from rlsac.tasks.line import LineTask

torch.set_num_threads(1)


def put(root: Path, rel: str, **values) -> None:
    p = root / rel / "summary.json"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(values))


@pytest.fixture
def tree(workdir):
    ev = workdir / "ev"
    put(ev, "lines/ransac/o0.1", mAA=0.8123, median_deg=0.0711, n_instances=50, iterations=150,
        data="data/lines/test_o0.1.h5", checkpoint=None)
    put(ev, "lines/ours/o0.7", mAA=0.7345, median_deg=0.0901, n_instances=50, iterations=150,
        data="data/lines/test_o0.7.h5", checkpoint="checkpoints/line_o0.7.pt")
    f = dict(mAA=0.5, median_R=1.234, median_t=2.345, n_instances=9, data="missing/test.h5", method="magsac")
    put(ev, "fundamental/magsac/i1000", mAA_R=0.6611, mAA_t=0.5522, **f)
    put(ev, "fundamental/magsac/i100", mAA_R=0.6011, mAA_t=0.5022, **f)
    put(ev, "fundamental/rlsac/i10", mAA_R=0.3011, mAA_t=0.2022, **f)
    put(ev, "ablation/full", mAA_R=0.7011, mAA_t=0.6022, **f)
    put(ev, "ablation/n200", mAA_R=0.6811, mAA_t=0.5822, **f)
    return workdir


def cell(df: pd.DataFrame, col: str, **where) -> float:
    m = pd.Series(True, index=df.index)
    for k, v in where.items():
        m &= df[k] == v
    assert m.sum() == 1, where
    return float(df.loc[m, col].iloc[0])


def test_table1_cells_paper_and_missing(tree):
    df = tables.table1("ev", "out")
    assert cell(df, "0.1 mAA", method="RANSAC", source="ours") == pytest.approx(0.8123)
    assert cell(df, "0.1 med", method="RANSAC", source="ours") == pytest.approx(0.0711)
    assert cell(df, "0.7 mAA", method="Ours", source="ours") == pytest.approx(0.7345)
    assert math.isnan(cell(df, "0.5 mAA", method="Ours", source="ours"))
    for label, rows in paper.TABLE1.items():
        assert cell(df, "0.7 mAA", method=label, source="paper") == rows[0.7][0]
    assert len(df.attrs["missing"]) == 5 * 7 - 2
    for extra in ("Oracle", "NG-RANSAC"):  # no paper row for our extra methods
        assert set(df.loc[df["method"] == extra, "source"]) == {"ours"}
    md = (tree / "out" / "table1_lines.md").read_text()
    assert "calibrated synthetic lines" in md and "0.812" in md and "0.608" in md and "–" in md
    assert (tree / "out" / "table1_lines.tex").read_text().count("--") > 10
    csv = pd.read_csv(tree / "out" / "table1_lines.csv")
    assert csv.shape == (8, 16) and csv["0.1 mAA"].iloc[0] == pytest.approx(0.8123)


def test_table1_paired_comparison_from_errors(tree):
    assert tables.table1("ev", "out").attrs["paired"] is None  # no errors.csv: no comparison, no note
    for method, errs in (("ransac", [0.02] * 5 + [1.0] * 5), ("ours", [0.02] * 10)):
        d = tree / "ev" / "lines" / method / "o0.2"
        d.mkdir(parents=True, exist_ok=True)
        pd.DataFrame({"instance": range(10), "err_deg": errs}).to_csv(d / "errors.csv", index=False)
    paired = tables.table1("ev", "out").attrs["paired"]
    assert list(paired["comparison"]) == ["Ours − RANSAC", "Ours-0.5 − RANSAC", "NG-RANSAC − RANSAC",
                                          "Ours − NG-RANSAC"]
    assert paired.loc[0, "o=0.2"].startswith("+0.500 [")
    assert paired.loc[0, "o=0.1"] == "–" and paired.loc[1, "o=0.2"] == "–" and paired.loc[3, "o=0.2"] == "–"
    d = tree / "ev" / "lines" / "ngransac" / "o0.2"  # NG-RANSAC (issue #29): 8 of 10 right
    d.mkdir(parents=True)
    pd.DataFrame({"instance": range(10), "err_deg": [0.02] * 8 + [1.0] * 2}).to_csv(d / "errors.csv", index=False)
    paired = tables.table1("ev", "out").attrs["paired"]
    assert paired.loc[2, "o=0.2"].startswith("+0.300 [") and paired.loc[3, "o=0.2"].startswith("+0.200 [")
    assert "Paired comparison" in (tree / "out" / "table1_lines.md").read_text()


def _line_errors(root: Path, d: str, rate: float, errs) -> None:
    out = root / "lines" / d / f"o{rate:g}"
    out.mkdir(parents=True, exist_ok=True)
    pd.DataFrame({"instance": range(len(errs)), "err_deg": errs}).to_csv(out / "errors.csv", index=False)


def test_table1_across_seed_section(tree):
    """Issue #27: Ours over its training seeds (ours, ours-s1, ours-s2) against RANSAC: the seed mean and SD of mAA
    and the difference of seed means with an interval that resamples seeds; a rate where a seed lacks results is
    left out, and one seed alone gives no section."""
    ev = tree / "ev"
    _line_errors(ev, "ransac", 0.3, [0.02] * 5 + [1.0] * 5)  # mAA 0.5
    _line_errors(ev, "ours", 0.3, [0.02] * 10)  # 1.0
    assert "Across training seeds" not in (tables.table1("ev", "out").attrs.get("caption") or "")
    assert "Across training seeds" not in (tree / "out" / "table1_lines.md").read_text()
    _line_errors(ev, "ours-s1", 0.3, [1.0] * 10)  # 0.0
    _line_errors(ev, "ours-s2", 0.3, [0.02] * 10)  # 1.0
    _line_errors(ev, "ours-s1", 0.7, [0.02] * 10)  # no seed 0 / RANSAC at 0.7: no row there
    assert tables.line_seed_runs(ev / "lines") == {"ours": ["ours", "ours-s1", "ours-s2"]}
    tables.table1("ev", "out")
    md = (tree / "out" / "table1_lines.md").read_text()
    rows = [line for line in md.splitlines() if line.startswith("| 0.")]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    # seed mAAs 1, 0, 1: mean 0.667, SD 0.577; minus RANSAC's 0.5; 2 of 3 seeds beat it
    assert cells[:5] == ["0.3", "Ours − RANSAC", "3 vs 1", "0.667 ± 0.577", "0.500"]
    assert cells[5].startswith("+0.167 [") and cells[6] == "0.67"
    for d in ("ours", "ours-s1", "ours-s2"):  # Ours-0.5 at its own rate: the same models as Ours, not compared
        _line_errors(ev, d.replace("ours", "ours-0.5"), 0.3, pd.read_csv(ev / "lines" / d / "o0.3" / "errors.csv")[
            "err_deg"].tolist())
    tables.table1("ev", "out")
    rows = [line for line in (tree / "out" / "table1_lines.md").read_text().splitlines() if line.startswith("| 0.")]
    assert [r.split("|")[2].strip() for r in rows] == ["Ours − RANSAC", "Ours-0.5 − RANSAC"]


def test_table2_and_table3(tree):
    df = tables.table2("ev", "out")
    assert cell(df, "mAA_R", method="MAGSAC++", source="ours") == pytest.approx(0.6611)
    assert cell(df, "median_t", method="MAGSAC++", source="paper") == paper.TABLE2["MAGSAC++"][3]
    assert math.isnan(cell(df, "mAA_R", method="Ours", source="ours"))
    assert "USAC_ACCURATE" in set(df["method"]) and "RANSAC (our batched torch)" in set(df["method"])
    md = (tree / "out" / "table2_fundamental.md").read_text()
    assert "0.661" in md and "0.760" in md and "–" in md and "missing/test.h5" in md
    df3 = tables.table3("ev", "out")
    full = df3[(df3["variant"] == "full") & (df3["source"] == "ours")]
    assert len(full) == 3 and (full["mAA_R"] == 0.7011).all()
    assert cell(df3, "mAA_t", variant="n200", source="ours") == pytest.approx(0.5822)
    assert cell(df3, "mAA_R", variant="no_descriptors", source="paper") == 0.702
    assert math.isnan(cell(df3, "mAA_R", variant="n300", source="ours"))
    for ext in ("md", "csv", "tex"):
        assert (tree / "out" / f"table3_ablation.{ext}").stat().st_size > 0


def test_empty_tree_does_not_crash(workdir, capsys):
    df = tables.table2("nothing", "out")
    assert df[df["source"] == "ours"]["mAA_R"].isna().all()
    assert "missing nothing/fundamental/rlsac/i1000/summary.json" in capsys.readouterr().out
    assert tables.metrics("nothing", "out") == {}  # only results that exist


def test_iterations_csv_and_metrics(tree):
    df = tables.iterations_csv("ev", "out")
    got = pd.read_csv(tree / "out" / "fundamental_iterations.csv")
    assert list(got.columns[:4]) == ["method", "iterations", "mAA_R", "mAA_t"]
    assert len(df) == len(got) == 3
    assert got[(got["method"] == "magsac") & (got["iterations"] == 100)]["mAA_R"].iloc[0] == pytest.approx(0.6011)
    m = tables.metrics("ev", "out")
    assert m["lines"]["ransac"]["o0.1"]["mAA"] == pytest.approx(0.8123)
    assert m["fundamental_1k"]["magsac"]["mAA_t"] == pytest.approx(0.5522)
    assert json.loads((tree / "out" / "metrics.json").read_text()) == m


def test_cli_table(tree):
    r = CliRunner().invoke(cli, ["table", "--which", "1", "--eval-root", "ev", "--out-dir", "out", "--no-tracking"])
    assert r.exit_code == 0, r.output
    assert "table1_lines.md" in r.output and "missing" in r.output
    assert (tree / "out" / "table1_lines.md").is_file() and (tree / "out" / "metrics.json").is_file()
    assert not (tree / "out" / "table2_fundamental.md").exists()


def tiny_checkpoint(path: Path) -> Path:
    task = LineTask()
    conf = config.to_dict(TrainConf())
    conf["policy"] = {**conf["policy"], "widths": [8, 8], "global_width": 8, "head_width": 8}
    actor = Actor(in_channels(task), config.build(PolicyConf, conf["policy"]))
    torch.save({"actor": actor.state_dict(), "conf": conf, "in_channels": in_channels(task), "step": 0, "val": {}},
               path)
    return path


def test_plot_iterations_and_line_steps(tree):
    data_conf = lines.LineDataConf(outlier_rate=0.5, n_instances=6, seed=1)
    lines.write(tree / "l.h5", lines.generate(data_conf), data_conf)
    ckpt = tiny_checkpoint(tree / "tiny.pt")
    s = figures.plot({"which": "iterations,line_steps", "eval_root": "ev", "reports_dir": "out", "out_dir": "figs",
                      "line_data": "l.h5", "line_checkpoint": str(ckpt), "line_steps": 4}, track=False)
    for name in ("fundamental_iterations", "line_steps"):
        for ext in ("png", "pdf"):
            assert (tree / "figs" / f"{name}.{ext}").stat().st_size > 1000
    assert s["notes"] == "none"
    s = figures.plot({"which": "line", "out_dir": "figs2", "line_data": "l.h5", "line_checkpoint": "",
                      "line_index": 2}, track=False)
    assert "no checkpoint" in s["notes"] and (tree / "figs2" / "line_steps.png").stat().st_size > 1000


def test_learning_curves_take_a_models_seeds_together(tmp_path, monkeypatch):
    """Issue #27: rlsac and rlsac-s1 are one model's two seeds: one table (steps x seeds) per fold, which the figure
    draws as the seed mean with its band; another model stays its own column."""
    from rlsac.reports import fold_figures

    def ck(vals, step):
        return {"history": [{"step": s, "charts/val_mAA": v, "charts/val_inlier_ratio": v / 2}
                            for s, v in zip((100, 200), vals, strict=True)], "step": step, "selection": "inlier_ratio"}

    root = tmp_path / "hard" / "castle"
    read = {root / "rlsac.pt": ck([0.2, 0.4], 200), root / "rlsac-s1.pt": ck([0.4, 0.2], 100),
            root / "rlsac-nosnn.pt": ck([0.1, 0.3], 200)}
    got = fold_figures.seed_curves(read, "charts/val_mAA")
    assert set(got) == {("rlsac", "hard/castle"), ("rlsac-nosnn", "hard/castle")}
    t = got[("rlsac", "hard/castle")]
    assert list(t.columns) == ["rlsac", "rlsac-s1"] and t.mean(axis=1).tolist() == pytest.approx([0.3, 0.3])
    drawn = []
    real_save = fold_figures._save
    monkeypatch.setattr(fold_figures, "_save", lambda fig, out, name: drawn.append(fig) or real_save(fig, out, name))
    files, _ = fold_figures.plot_learning_curves(read, tmp_path / "fig")
    assert [Path(f).name for f in files] == ["learning_curves.png", "learning_curves.pdf"]
    # issue #63: a row per model (no empty cell), every panel titled, one legend for the figure
    titles = [ax.get_title() for ax in drawn[0].axes]
    assert titles == ["rlsac (2 seeds, kept by inlier_ratio): validation mAA@10°",
                      "rlsac (2 seeds, kept by inlier_ratio): validation mean inlier ratio",
                      "rlsac-nosnn (1 seed, kept by inlier_ratio): validation mAA@10°",
                      "rlsac-nosnn (1 seed, kept by inlier_ratio): validation mean inlier ratio"]
    assert all(ax.get_legend() is None for ax in drawn[0].axes) and len(drawn[0].legends) == 1
    assert [t.get_text() for t in drawn[0].legends[0].get_texts()] == ["hard/castle", "min–max over seeds",
                                                                      "kept actor"]


def test_table1_ngransac_row_over_its_seeds(tree):
    """Issue #29 on lines: NG-RANSAC's training seeds (ngransac-s<seed>) are taken like Ours', and Ours is compared
    with it over both rows' seeds."""
    ev = tree / "ev"
    _line_errors(ev, "ransac", 0.5, [0.02] * 5 + [1.0] * 5)  # 0.5
    for d, errs in (("ours", [0.02] * 10), ("ours-s1", [0.02] * 9 + [1.0]), ("ngransac", [0.02] * 6 + [1.0] * 4),
                    ("ngransac-s1", [0.02] * 8 + [1.0] * 2)):
        _line_errors(ev, d, 0.5, errs)
    assert tables.line_seed_runs(ev / "lines") == {"ours": ["ours", "ours-s1"], "ngransac": ["ngransac", "ngransac-s1"]}
    tables.table1("ev", "out")
    rows = {r.split("|")[2].strip(): [c.strip() for c in r.strip("|").split("|")]
            for r in (tree / "out" / "table1_lines.md").read_text().splitlines() if r.startswith("| 0.5")}
    assert set(rows) == {"Ours − RANSAC", "NG-RANSAC − RANSAC", "Ours − NG-RANSAC"}
    # seed means: Ours 0.95, NG-RANSAC 0.7: +0.25 over two seeds each
    assert rows["Ours − NG-RANSAC"][2:5] == ["2 vs 2", "0.950 ± 0.071", "0.700 ± 0.141"]
    assert rows["Ours − NG-RANSAC"][5].startswith("+0.250 [")


def test_cli_table_failing_half_way_leaves_every_table_as_it_was(tree, monkeypatch):
    """rlsac table writes its outputs as one set (io.all_or_nothing): a failure after Table 1 was built (here the
    claims) writes none of them, and the tables already there keep their bytes."""
    from rlsac.errors import RlsacError
    from rlsac.reports import claims

    out = tree / "out"
    out.mkdir()
    (out / "table1_lines.md").write_text("the record's table\n")

    def broken(*args, **kwargs):
        raise RlsacError("a claim's rows could not be read")

    monkeypatch.setattr(claims, "build", broken)
    r = CliRunner().invoke(cli, ["table", "--which", "all", "--eval-root", "ev", "--out-dir", "out", "--no-tracking"])
    assert r.exit_code == 2 and "error: a claim's rows could not be read" in r.output, r.output
    assert sorted(p.name for p in out.iterdir()) == ["table1_lines.md"]
    assert (out / "table1_lines.md").read_text() == "the record's table\n"


def test_figure_4_shows_the_papers_rows_and_the_appendix_every_row(tmp_path, monkeypatch):
    """Issue #47: Figure 4 (folds_iterations) draws the paper's methods and our controls only; every other row (here
    PROSAC, a peer) is in the appendix figure folds_iterations_all. Issue #63: one legend for the figure (a legend
    per panel repeated seven entries eight times), every panel titled."""
    import pandas as pd

    from rlsac.reports import fold_figures

    rows = [{"regime": "hard", "method": m, "iterations": it, "mAA_R": 0.5, "mAA_t": 0.4, "n_pairs": 6,
             "dR": 0.01, "dR_lo": -0.01, "dR_hi": 0.03, "dt": 0.0, "dt_lo": -0.02, "dt_hi": 0.02}
            for m in ("rlsac", "uniform", "magsac", "prosac") for it in (10, 100)]
    drawn = {}
    real_save = fold_figures._save

    def save(fig, out_dir, name):
        drawn[name] = fig
        return real_save(fig, out_dir, name)

    monkeypatch.setattr(fold_figures, "_save", save)
    files, _ = fold_figures.plot_folds_iterations(pd.DataFrame(rows), tmp_path)
    assert [Path(f).name for f in files] == ["folds_iterations.png", "folds_iterations.pdf",
                                             "folds_iterations_all.png", "folds_iterations_all.pdf"]
    for name, methods in (("folds_iterations", ["magsac", "rlsac", "uniform"]),
                          ("folds_iterations_all", ["magsac", "prosac", "rlsac", "uniform"])):
        fig = drawn[name]
        assert len(fig.axes) == 4 and all(ax.get_legend() is None for ax in fig.axes)
        assert [len(fig.legends)] == [1] and sorted(t.get_text() for t in fig.legends[0].get_texts()) == methods
        assert [ax.get_title() for ax in fig.axes] == [
            "hard regime (6 test pairs): mAA@10° of R", "hard regime (6 test pairs): mAA@10° of t",
            "hard regime: RLSAC − method in R (95% interval)", "hard regime: RLSAC − method in t (95% interval)"]
    diffs = drawn["folds_iterations"].axes[2]  # RLSAC − magsac and − uniform, each with its interval
    assert sorted(c.get_label() for c in diffs.containers) == ["magsac", "uniform"]
