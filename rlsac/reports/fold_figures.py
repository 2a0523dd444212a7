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

from rlsac import checkpoint  # noqa: E402
from rlsac.errors import RlsacError  # noqa: E402
from rlsac.reports import figfile  # noqa: E402
from rlsac.results import read_table  # noqa: E402

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
    regimes = sorted(df["regime"].unique())
    methods = list(dict.fromkeys(df["method"]))
    style = _styles(methods, fixed)
    diffs = "dR" in df and df["dR"].notna().any()  # the table's paired differences to RLSAC, with 95% intervals
    per = 2 if diffs else 1
    width = 14 if fixed else 15  # room for the legends beside the panels
    fig, axes = plt.subplots(per * len(regimes), 2, figsize=(width, 4 * per * len(regimes)), squeeze=False,
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
                ax.plot(g["iterations"], g[col], marker=marker, color=colour, label=m)
            ax.set_xscale("log")
            ax.set_xlabel("iterations (hypotheses per pair)")
            ax.set_ylabel(f"mAA@10° {what}")
            ax.set_title(f"{regime} regime ({int(d['n_pairs'].max())} test pairs): {what}", fontsize=10)
            ax.grid(alpha=0.3)
            _legend(ax, fixed)
    return _save(fig, out_dir, name)


def _legend(ax, fixed: bool) -> None:
    """Every panel its own legend, beside it: inside, it covered lines or bands somewhere (issue #47)."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7 if fixed else 6, borderaxespad=0)


def _plot_diffs(axes, d: pd.DataFrame, regime: str, rows: list[str], style: dict) -> None:
    """RLSAC minus each of ``rows`` against the budget, pooled, with the paired 95% interval as a band (the table
    stores method - RLSAC; the sign is flipped so that above zero means RLSAC is ahead)."""
    fixed = all(style[m] == STYLE.get(m, ("black", ".")) for m in rows)
    for c, (col, what) in enumerate((("dR", "R"), ("dt", "t"))):
        ax = axes[c]
        for m in rows:
            g = d[d["method"] == m].sort_values("iterations")
            if g.empty or g[col].isna().all():
                continue
            colour, marker = style[m]
            ax.plot(g["iterations"], -g[col], marker=marker, color=colour, label=f"RLSAC − {m}")
            ax.fill_between(g["iterations"], -g[f"{col}_hi"], -g[f"{col}_lo"], color=colour, alpha=0.12, lw=0)
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("iterations (hypotheses per pair)")
        ax.set_ylabel(f"RLSAC − method, mAA@10° {what}")
        ax.set_title(f"{regime}: RLSAC − method in {what}, 95% interval over pairs", fontsize=10)
        ax.grid(alpha=0.3)
        _legend(ax, fixed)


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
    from rlsac.protocol import split_seed

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
    column per model, one colour per fold; a model trained with several seeds (<model>-s<seed>, issue #27) is drawn
    as the seed mean with its min-max band, each seed's kept actor circled."""
    from rlsac.protocol import split_seed

    read = ckpt_root if isinstance(ckpt_root, dict) else read_checkpoints(ckpt_root)
    kept = {p.stem + "@" + f"{p.parent.parent.name}/{p.parent.name}": ck.get("step") for p, ck in read.items()}
    selection = {split_seed(p.stem)[0]: ck.get("selection", "val_mAA") for p, ck in read.items()}
    models = sorted(selection)
    # a grid (issue #47: eight models made one 4547 x 847 px row): at most four models a row, each its two panels
    # (validation mAA over validation inlier ratio) in one column
    ncols = min(4, len(models))
    nrows = -(-len(models) // ncols)
    fig, grid = plt.subplots(2 * nrows, ncols, figsize=(4.6 * ncols, 6.4 * nrows), squeeze=False, layout="constrained")
    axes = {(r, c): grid[2 * (c // ncols) + r, c % ncols] for c in range(len(models)) for r in range(2)}
    for k in range(len(models), nrows * ncols):  # empty cells of the last row
        grid[2 * (k // ncols), k % ncols].set_visible(False)
        grid[2 * (k // ncols) + 1, k % ncols].set_visible(False)
    for r, key in enumerate(("charts/val_mAA", "charts/val_inlier_ratio")):
        for (model, where), table in seed_curves(read, key).items():
            ax = axes[r, models.index(model)]
            label = where + (f" ({table.shape[1]} seeds)" if table.shape[1] > 1 else "")
            line, = ax.plot(table.index, table.mean(axis=1), marker=".", label=label)
            if table.shape[1] > 1:
                ax.fill_between(table.index, table.min(axis=1), table.max(axis=1), alpha=0.2, color=line.get_color(),
                                lw=0)
            for run in table.columns:
                step = kept.get(f"{run}@{where}")
                if step in table.index:
                    ax.plot([step], [table.loc[step, run]], "o", mfc="none", ms=10, color=line.get_color())
    for c, model in enumerate(models):
        axes[0, c].set_title(f"{model}\n(kept actors circled; selection: {selection[model]})", fontsize=9)
        axes[0, c].set_ylabel("val. mAA@10° (seed mean, min-max)", fontsize=8)
        axes[1, c].set_ylabel("val. mean inlier ratio", fontsize=8)
        for r in range(2):
            axes[r, c].set_xlabel("SAC step", fontsize=8)
            axes[r, c].tick_params(labelsize=7)
            axes[r, c].grid(alpha=0.3)
        axes[0, c].legend(fontsize=6)
    return _save(fig, out_dir, "learning_curves"), ""
