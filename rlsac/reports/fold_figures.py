"""Figures of the fold benchmark: pooled mAA against the budget, and the models' learning curves.

* ``folds_iterations``: reports/folds_iterations.csv (``rlsac table --which folds``), one panel per regime and
  error (R, t), every method's pooled mAA@10° against the iteration budget (log x); ``essential_iterations``:
  the same of Table E (reports/essential_iterations.csv, ``rlsac table --which essential``).
* ``learning_curves``: the validation history every fold checkpoint carries (``history``: validation mAA and
  mean inlier ratio of the final hypotheses per SAC step, the same values MLflow logs as ``charts/val_*``),
  one line per fold, one column per model; the kept step is marked.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from rlsac.errors import RlsacError  # noqa: E402
from rlsac.evaluation.results import read_table  # noqa: E402
from rlsac.reports import figfile  # noqa: E402
from rlsac.rl import checkpoint  # noqa: E402

STYLE = {"uniform": ("tab:blue", "x"), "guided": ("tab:cyan", "<"), "prosac": ("olive", ">"),
         "ransac": ("tab:purple", "o"), "opencv_ransac": ("tab:gray", "s"),
         "usac": ("tab:orange", "^"), "usac_accurate": ("tab:brown", "v"), "magsac": ("tab:green", "D"),
         "rlsac": ("tab:red", "*"), "rlsac-fast": ("salmon", "X"), "rlsac-nosnn": ("black", "1"),
         "usac-nolo": ("tab:orange", "3"), "magsac-nolo": ("tab:green", "4"), "prosac-nolo": ("olive", "+"),
         "ransac-lo": ("violet", "h"), "uniform-lo": ("royalblue", "8"), "guided-lo": ("darkcyan", "d"),
         "rlsac-lo": ("crimson", "p"), "degensac": ("teal", "P"), "poselib": ("tab:pink", "H"),
         "ngransac": ("darkgoldenrod", "d"), "ngransac-lo": ("goldenrod", "d")}
# the paired-difference panels (Figure 4 on the folds): RLSAC against the controls, the strongest rows of each arm and
# the peers of issue #29
DIFF_ROWS = ("uniform", "guided", "ransac", "usac-nolo", "magsac-nolo", "prosac-nolo", "prosac", "magsac", "degensac",
             "poselib", "ngransac")


def _save(fig, out_dir: Path, name: str) -> list[str]:
    return figfile.save(fig, out_dir, name, dpi=130)


COLUMNS = ("regime", "method", "iterations", "mAA_R", "mAA_t", "n_pairs")  # what the iterations figure reads
NUMERIC = ("iterations", "mAA_R", "mAA_t", "n_pairs")


def read_iterations(csv: str | Path, name: str = "folds_iterations") -> pd.DataFrame:
    """A fold table's iterations CSV, read and checked (readable, not empty, the ``COLUMNS``) -> the frame."""
    csv = Path(csv)
    if not csv.is_file():
        raise RlsacError(f"{csv}: no such file (run `rlsac table --which {name.split('_')[0]}` first)")
    try:
        df = pd.read_csv(csv, nrows=0)
    except (ValueError, OSError) as e:  # pandas' ParserError and EmptyDataError are ValueErrors
        raise RlsacError(f"{csv}: not a readable CSV ({e.__class__.__name__})") from None
    missing = [c for c in COLUMNS if c not in df]
    if missing:
        raise RlsacError(f"{csv}: no column(s) {missing} (run `rlsac table --which {name.split('_')[0]}` again)")
    df = read_table(csv, NUMERIC, "iterations CSV")  # NaN in a plotted column failed inside matplotlib
    if df.empty:
        raise RlsacError(f"{csv}: no results to plot")
    return df


# Figure 4 proper (issue #47): the paper's methods (OpenCV's RANSAC, USAC, MAGSAC++ as the tutorial calls them), RLSAC,
# and our controls (uniform and SNN-guided sets in RLSAC's environment, our RANSAC); every other row goes to the
# appendix figure <name>_all, so that a panel stays readable (26 lines, five of them black, before)
PAPER_ROWS = ("opencv_ransac", "usac", "magsac", "ransac", "uniform", "guided", "rlsac")
PAPER_DIFF_ROWS = ("opencv_ransac", "usac", "magsac", "ransac", "uniform", "guided")
MARKERS = ("o", "s", "^", "v", "D", "<", ">", "p", "h", "X", "P", "*", "d", "8", "H")


def _styles(methods: list[str], fixed: bool) -> dict[str, tuple[str, str]]:
    """A colour and marker per method: ``STYLE``'s for the paper figure (fixed, distinct there); for the appendix one
    of tab20's colours and a marker each, in order, so that no two of its rows look alike."""
    if fixed:
        return {m: STYLE.get(m, ("black", ".")) for m in methods}
    cmap = plt.get_cmap("tab20")
    return {m: (cmap(i % 20), MARKERS[i % len(MARKERS)]) for i, m in enumerate(methods)}


def plot_folds_iterations(csv: str | Path | pd.DataFrame, out_dir: Path, name: str = "folds_iterations"
                          ) -> tuple[list[str], str]:
    """Pooled mAA against the budget from a fold table's iterations CSV (Table 2 folds: folds_iterations,
    Table E: essential_iterations; or the frame ``read_iterations`` read), saved as ``name`` with the paper's rows
    and the controls (``PAPER_ROWS``), and as ``<name>_all`` with every row (the appendix)."""
    df = csv if isinstance(csv, pd.DataFrame) else read_iterations(csv, name)
    main = [m for m in PAPER_ROWS if m in set(df["method"])]
    paths = _iterations_figure(df[df["method"].isin(main)], out_dir, name, PAPER_DIFF_ROWS, fixed=True,
                               title="the paper's methods and our controls")
    paths += _iterations_figure(df, out_dir, f"{name}_all", DIFF_ROWS + PAPER_DIFF_ROWS, fixed=False,
                                title="every row (appendix)")
    return paths, ""


def _iterations_figure(df: pd.DataFrame, out_dir: Path, name: str, diff_rows, fixed: bool, title: str) -> list[str]:
    """One row of panels per regime (R, t), and under it RLSAC − each of ``diff_rows`` when the table has the paired
    differences; every panel titled, one legend for the figure (a method has one colour and marker in every panel)."""
    regimes = sorted(df["regime"].unique())
    methods = list(dict.fromkeys(df["method"]))
    style = _styles(methods, fixed)
    diffs = "dR" in df and df["dR"].notna().any()  # the table's paired differences to RLSAC, with 95% intervals
    per = 2 if diffs else 1
    fig, axes = plt.subplots(per * len(regimes), 2, figsize=(12, 3.6 * per * len(regimes) + 1.2), squeeze=False,
                             layout="constrained")
    fig.suptitle(f"Pooled mAA@10° against the budget: {title}")
    for r, regime in enumerate(regimes):
        d = df[df["regime"] == regime]
        if diffs:
            _plot_diffs(axes[per * r + 1], d, regime, [m for m in dict.fromkeys(diff_rows) if m in methods], style)
        for c, (col, what) in enumerate((("mAA_R", "R"), ("mAA_t", "t"))):
            ax = axes[per * r, c]
            for m, g in d.groupby("method", sort=False):
                g = g.sort_values("iterations")
                colour, marker = style[m]
                ax.plot(g["iterations"], g[col], marker=marker, color=colour, label=m, lw=1.6 if m == "rlsac" else 1)
            ax.set_xscale("log")
            ax.set_xlabel("iterations (hypotheses per pair)")
            ax.set_ylabel(f"mAA@10° {what}")
            ax.set_title(f"{regime} regime ({int(d['n_pairs'].max())} test pairs): mAA@10° of {what}")
            ax.grid(alpha=0.3)
    _shared_legend(fig, style, methods)
    return _save(fig, out_dir, name)


def _shared_legend(fig, style: dict, methods: list[str]) -> None:
    """One legend for every panel, under them (a legend per panel repeated seven entries eight times, issue #63)."""
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=style[m][0], marker=style[m][1], label=m) for m in methods]
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(methods), 8), fontsize=9,
               title="method (difference panels: RLSAC − method, the bar its paired 95% interval over pairs)",
               title_fontsize=9)


def _plot_diffs(axes, d: pd.DataFrame, regime: str, rows: list[str], style: dict) -> None:
    """RLSAC minus each of ``rows`` against the budget, pooled, with the paired 95% interval as an error bar, each
    method's bars nudged sideways so that they do not hide each other (bands over bands did; the table stores
    method - RLSAC, the sign is flipped so that above zero means RLSAC is ahead)."""
    import numpy as np

    shown = [m for m in rows if not d[d["method"] == m]["dR"].isna().all()]
    for c, (col, what) in enumerate((("dR", "R"), ("dt", "t"))):
        ax = axes[c]
        for k, m in enumerate(shown):
            g = d[d["method"] == m].sort_values("iterations")
            colour, marker = style[m]
            # at most a tenth of a decade either side, whatever the number of rows
            nudge = 10 ** (min(0.025, 0.2 / max(len(shown), 1)) * (k - (len(shown) - 1) / 2))
            x, y = g["iterations"].to_numpy() * nudge, -g[col].to_numpy()
            err = np.vstack([y - (-g[f"{col}_hi"].to_numpy()), -g[f"{col}_lo"].to_numpy() - y])
            ax.errorbar(x, y, yerr=err, marker=marker, color=colour, ms=4, lw=1, elinewidth=0.8, capsize=2,
                        label=m)
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("iterations (hypotheses per pair)")
        ax.set_ylabel(f"RLSAC − method, mAA@10° {what}")
        ax.set_title(f"{regime} regime: RLSAC − method in {what} (95% interval)")
        ax.grid(alpha=0.3)


def read_checkpoints(ckpt_root: str | Path) -> dict[Path, dict]:
    """Every fold checkpoint <root>/<regime>/<fold>/<model>.pt, read (a file that is not a checkpoint fails
    here, before ``rlsac plot`` draws anything) -> {path: checkpoint dict}."""
    root = Path(ckpt_root)
    ckpts = sorted(root.glob("*/*/*.pt")) if root.is_dir() else []
    ckpts = [p for p in ckpts if not p.name.endswith(".state.pt")]
    if not ckpts:
        raise RlsacError(f"{root}: no fold checkpoints (run `rlsac folds --stage train` first)")
    out = {}
    for p in ckpts:
        ck = checkpoint.read(p)
        if not isinstance(ck.get("history", []), list):
            raise RlsacError(f"{p}: not an rlsac checkpoint (its history is a {type(ck['history']).__name__})")
        out[p] = ck
    return out


def seed_curves(read: dict[Path, dict], key: str) -> dict[tuple[str, str], pd.DataFrame]:
    """(model, regime/fold) -> steps x seeds table of ``key`` from the checkpoints' validation histories; the rows
    of a model's other training seeds (<model>-s<seed>) are columns of the model's table (issue #27)."""
    from rlsac.layout.protocol import split_seed

    out: dict[tuple[str, str], list[pd.Series]] = {}
    def order(p: Path) -> tuple[str, str, int]:  # the model itself (its recipe's seed) first, then by seed
        base, seed = split_seed(p.stem)
        return str(p.parent), base, -1 if seed is None else seed

    for p in sorted(read, key=order):
        hist = pd.DataFrame(read[p].get("history") or [])
        if hist.empty or key not in hist:
            continue
        where = (split_seed(p.stem)[0], f"{p.parent.parent.name}/{p.parent.name}")
        out.setdefault(where, []).append(hist.set_index("step")[key].rename(p.stem))
    return {k: pd.concat(v, axis=1) for k, v in out.items()}


def plot_learning_curves(ckpt_root: str | Path | dict, out_dir: Path) -> tuple[list[str], str]:
    """The validation curves of every fold checkpoint under ``ckpt_root`` (or of ``read_checkpoints``' dict): one
    row per model, its validation mAA beside its validation inlier ratio, one colour per fold (the same in every
    panel, one legend for the figure); a model trained with several seeds (<model>-s<seed>, issue #27) is drawn as
    the seed mean with its min-max band, each seed's kept actor circled."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from rlsac.layout.protocol import split_seed

    read = ckpt_root if isinstance(ckpt_root, dict) else read_checkpoints(ckpt_root)
    kept = {p.stem + "@" + f"{p.parent.parent.name}/{p.parent.name}": ck.get("step") for p, ck in read.items()}
    selection = {split_seed(p.stem)[0]: ck.get("selection", "val_mAA") for p, ck in read.items()}
    models = sorted(selection)
    curves = {key: seed_curves(read, key) for key in KEYS}
    folds = sorted({where for table in curves.values() for _, where in table})
    colour = {f: plt.get_cmap("tab10")(i % 10) for i, f in enumerate(folds)}
    # a row per model, no empty cell (issue #63: a 4 x 4 grid of 14 panels, the inlier-ratio panels untitled)
    fig, axes = plt.subplots(len(models), 2, figsize=(11, 2.5 * len(models) + 1.0), squeeze=False,
                             layout="constrained")
    fig.suptitle("Validation curves of the fold models (params.yaml folds.train): seed mean, min–max band over "
                 "seeds, kept actor circled")
    for c, key in enumerate(KEYS):
        for (model, where), table in curves[key].items():
            ax = axes[models.index(model), c]
            ax.plot(table.index, table.mean(axis=1), marker=".", ms=4, color=colour[where])
            if table.shape[1] > 1:
                ax.fill_between(table.index, table.min(axis=1), table.max(axis=1), alpha=0.15, color=colour[where],
                                lw=0)
            for run in table.columns:
                step = kept.get(f"{run}@{where}")
                if step in table.index:
                    ax.plot([step], [table.loc[step, run]], "o", mfc="none", ms=8, color=colour[where])
    for r, model in enumerate(models):
        seeds = max((t.shape[1] for (m, _), t in curves[next(iter(KEYS))].items() if m == model), default=1)
        for c, key in enumerate(KEYS):
            ax = axes[r, c]
            ax.set_title(f"{model} ({seeds} seed{'s' if seeds > 1 else ''}, kept by {selection[model]}): "
                         f"{KEYS[key]}", fontsize=10)
            ax.set_ylabel(KEYS[key], fontsize=9)
            ax.set_xlabel("SAC step", fontsize=9)
            ax.grid(alpha=0.3)
    handles = [Line2D([], [], color=colour[f], marker=".", label=f) for f in folds]
    handles += [Patch(color="grey", alpha=0.3, label="min–max over seeds"),
                Line2D([], [], ls="", marker="o", mfc="none", color="grey", label="kept actor")]
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize=9)
    return _save(fig, out_dir, "learning_curves"), ""


KEYS = {"charts/val_mAA": "validation mAA@10°", "charts/val_inlier_ratio": "validation mean inlier ratio"}
