"""The paper's figures from our results: ``plot(options)`` is what ``rlsac plot --set key=value`` calls.

Figures (PNG + PDF in ``out_dir``, logged to the MLflow experiment "figures"):

* ``fundamental_iterations``: mAA@10 deg of R and t against the iteration budget (log x), every method
  found under ``<eval_root>/fundamental/<method>/i<iterations>/summary.json`` (via the iterations CSV),
  with the paper's 1k-iteration numbers (Table 2) as crosses;
* ``line_steps``: one synthetic line instance, the policy's minimal sets step by step in one episode;
* ``fundamental_pair``: one real image pair, the final RLSAC estimate (minimal set and inliers);
* ``fundamental_steps``: the same pair, step by step in one episode.

Inputs follow the recorded provenance, never whether ``data/`` happens to exist: a missing line file is
regenerated in a temporary folder from the ``rlsac lines-data`` stage that ``dvc.lock`` records for it and
checked against the recorded hash (``rlsac.reports.provenance``); a missing checkpoint, prepared
two-view file or image is an error (the prepared file comes from ``dvc repro prepare_fundamental@test``),
checked for every requested figure before anything is drawn. All figures are drawn into a temporary folder
and moved into ``out_dir`` only when every one succeeded: a failing ``rlsac plot`` leaves the committed
figures untouched. An empty checkpoint option (``--set line_checkpoint=``) draws uniform random minimal
sets (RANSAC) instead of a policy, and says so in the title. Options (all optional):

    which                  "all" or a comma list of the figures' names: folds, curves, essential, line, pair,
                           steps, iterations (``SHORT``), or the file names above
    out_dir                reports/figures
    eval_root, reports_dir reports/eval, reports (the iterations table is rebuilt from the summaries in
                           memory; reports_dir is unused and kept for old command lines)
    iterations_csv         read this CSV instead of rebuilding it
    line_data              data/lines/test_o0.7.h5 (missing: regenerated as recorded in dvc.lock)
    line_checkpoint        checkpoints/line_o0.7.pt
    line_index             "auto" (largest error drop among the first 64 instances) or an index
    line_steps             6 panels
    fundamental_data       data/folds/hard/fountain/test.h5
    fundamental_checkpoint checkpoints/folds/hard/fountain/rlsac.pt
    pair                   "auto" (the pair whose ground-truth inlier rate, Sampson < 2 px to the true F,
                           is closest to 0.5: a pair with visible outliers) or an index into the file
    image_root             images under <image_root>/<scene>/images/<id>.jpg [default: attrs root/split]
    fundamental_iterations 1000
    fundamental_steps      6 panels
    seed, device           0, cpu
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from rlsac.errors import RlsacError  # noqa: E402
from rlsac.reports import figfile  # noqa: E402

FIGURES = ("fundamental_iterations", "line_steps", "fundamental_pair", "fundamental_steps", "folds_iterations",
           "learning_curves", "essential_iterations")
# "all": every figure the pipeline draws; fundamental_iterations (the retired 87-pair split's budgets) by name only
ALL = tuple(f for f in FIGURES if f != "fundamental_iterations")
SHORT = {"iterations": "fundamental_iterations", "line": "line_steps", "pair": "fundamental_pair",
         "steps": "fundamental_steps", "folds": "folds_iterations", "curves": "learning_curves",
         "essential": "essential_iterations"}
# the names the docs use (docs/commands.md), each with its figure's file name: what an error lists
KNOWN = "all, " + ", ".join(f"{k} ({v})" for k, v in SHORT.items())
DEFAULTS: dict[str, Any] = {
    "which": "all",
    "out_dir": "reports/figures",
    "eval_root": "reports/eval",
    "reports_dir": "reports",
    "iterations_csv": None,
    "folds_iterations_csv": "reports/folds_iterations.csv",  # rlsac table --which folds
    "essential_iterations_csv": "reports/essential_iterations.csv",  # rlsac table --which essential
    "folds_checkpoints": "checkpoints/folds",  # <regime>/<fold>/<model>.pt with their validation history
    "line_data": "data/lines/test_o0.7.h5",
    "line_checkpoint": "checkpoints/line_o0.7.pt",
    "line_index": "auto",
    "line_steps": 6,
    # a pair of the fountain fold's test building and that fold's RLSAC model (the 87-pair paper split is retired)
    "fundamental_data": "data/folds/hard/fountain/test.h5",
    "fundamental_checkpoint": "checkpoints/folds/hard/fountain/rlsac.pt",
    "pair": "auto",
    "image_root": None,
    "fundamental_iterations": 1000,
    "fundamental_steps": 6,
    "seed": 0,
    "device": "cpu",
}
METHOD_STYLE = {  # directory -> (label, colour, marker)
    "opencv_ransac": ("RANSAC (OpenCV)", "tab:gray", "s"),
    "usac": ("USAC (OpenCV)", "tab:orange", "^"),
    "usac_accurate": ("USAC_ACCURATE (OpenCV)", "tab:brown", "v"),
    "magsac": ("MAGSAC++ (OpenCV)", "tab:green", "D"),
    "ransac": ("RANSAC (ours, torch)", "tab:purple", "o"),
    "rlsac": ("RLSAC (ours)", "tab:red", "*"),
}
PAPER_ROW = {"opencv_ransac": "RANSAC", "usac": "USAC", "magsac": "MAGSAC++", "rlsac": "Ours"}
STYLE = {"font.size": 11, "axes.titlesize": 11, "axes.labelsize": 11, "legend.fontsize": 10,
         "figure.titlesize": 13}


# ------------------------------------------------------------------------------------------ helpers


RESIDUAL_LABEL = {"sampson": "Sampson, px", "sampson_sq": "squared Sampson, px²", "symmetric": "symmetric epipolar, px"}

def _options(options: dict[str, Any]) -> dict[str, Any]:
    from rlsac.config import SEED_RANGE, check_mapping

    options = check_mapping(options, DEFAULTS, "plot",  # types and ranges, as rlsac.config.build does
                            types={"which": str | list[str], "line_index": int | str, "pair": int | str,
                                   "iterations_csv": str, "image_root": str},
                            ranges={"line_steps": "[1, inf)", "fundamental_steps": "[1, inf)",
                                    "fundamental_iterations": "[1, inf)", "seed": SEED_RANGE,
                                    "device": ("auto", "cpu", "cuda")})
    o = {**DEFAULTS, **{k: v for k, v in options.items() if v is not None}}
    which = o["which"]
    if isinstance(which, str):
        which = [w.strip() for w in which.split(",") if w.strip()]
    names = []
    for w in which:
        if w == "all":
            names += list(ALL)
        elif w in FIGURES or w in SHORT:
            names.append(SHORT.get(w, w))
        else:
            raise RlsacError(f"unknown figure {w!r}; which= takes {KNOWN}")
    if not names:
        raise RlsacError(f"which names no figure; which= takes {KNOWN}")
    o["which"] = list(dict.fromkeys(names))
    for key in ("line_index", "pair"):  # an index, or "auto" (the instance the figure picks)
        if isinstance(o[key], str) and o[key] != "auto":
            raise RlsacError(f"plot.{key} must be an integer or 'auto', got {o[key]!r}")
    from rlsac.devices import device_name

    device_name(o["device"])  # cuda without a GPU: the device is named, before a checkpoint is read onto it
    return o


def _save(fig, out_dir: Path, name: str) -> list[str]:
    return figfile.save(fig, out_dir, name, dpi=150)


def _load_policy(path: str | None, task_name: str, device: str):
    """-> (actor, task, env conf, note), or (None, default task, EnvConf(), why) when no checkpoint is asked for
    (empty option). A checkpoint path that does not exist is an error, never a silent fallback."""
    from rlsac.rl.checkpoint import check_reads, env_conf, load_actor, task_options
    from rlsac.rl.rollout import in_channels
    from rlsac.tasks import task_from

    if not path:
        return None, task_from(task_name), env_conf({}), "no checkpoint asked for: uniform random minimal sets"
    if not Path(path).is_file():
        raise RlsacError(f"{path}: no such checkpoint (an empty option draws uniform random minimal sets instead)")
    actor, conf = load_actor(path, device)
    conf = dict(conf or {})
    task = task_from(task_name, task_options(conf))
    # an NG-RANSAC network without its 'kind' loads as an actor: a shape RuntimeError in the first step (issue #49)
    check_reads(path, actor, in_channels(task), "rlsac")
    return actor, task, env_conf(conf), ""


def _to_cpu(x):
    if torch.is_tensor(x):
        return x.cpu()
    if isinstance(x, dict):
        return {k: _to_cpu(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_to_cpu(v) for v in x]
    return x


def _rlsac_rollout(task, batch, actor, env, seed: int, iterations: int) -> dict:
    """rlsac_estimate with record=True on the actor's device (option ``device``: the batch and a seeded generator
    go there), its output on the CPU, where the figure is drawn."""
    from rlsac.rl.rollout import rlsac_estimate

    dev = next(actor.parameters()).device
    on_dev = {k: v.to(dev) if torch.is_tensor(v) else v for k, v in batch.items()}
    return _to_cpu(rlsac_estimate(task, on_dev, actor, iterations=iterations, env_conf=env,
                                  generator=torch.Generator(device=dev).manual_seed(seed), record=True))


def _episode(task, batch, actor, env, seed: int) -> list[dict]:
    """One episode per batch row: per step minimal_set (B, m), hyp, inliers (B, N), count (B,); CPU tensors."""
    steps = env.steps_per_episode
    if actor is not None:
        return _rlsac_rollout(task, batch, actor, env, seed, steps)["steps"]
    gen = torch.Generator().manual_seed(seed)
    from rlsac.estimation.lo import score_sets
    from rlsac.estimation.sampling import gather_points, uniform_minimal_sets

    coords, mask = batch["coords"], batch["mask"]
    idx = uniform_minimal_sets(mask, task.sample_size, steps, gen)  # (B, steps, m)
    out = []
    for t in range(steps):
        hyps, valid, res, _ = score_sets(task, gather_points(coords, idx[:, t, None]), coords, mask)
        hyps, valid, res = hyps[:, 0], valid[:, 0], res[:, 0]
        inl = (res <= task.threshold) & mask & valid[:, None]
        out.append({"minimal_set": idx[:, t], "hyp": hyps, "inliers": inl, "count": inl.sum(-1)})
    return out


def _pick_steps(n_steps: int, k: int) -> list[int]:
    k = max(1, min(int(k), n_steps))
    return sorted({int(round(x)) for x in np.linspace(0, n_steps - 1, k)})


def _grid(k: int) -> tuple[int, int]:
    cols = min(3, k)
    return math.ceil(k / cols), cols


# ----------------------------------------------------------------------------- iterations figure


def plot_iterations(df: pd.DataFrame, out_dir: Path) -> tuple[list[str], str]:
    from rlsac.reports import paper

    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), sharey=True)
        handles = []
        for ax, key, what in ((axes[0], "mAA_R", "rotation R"), (axes[1], "mAA_t", "translation direction t")):
            for m, (label, colour, marker) in METHOD_STYLE.items():
                d = df[df["method"] == m].sort_values("iterations")
                if len(d):
                    ax.plot(d["iterations"], d[key], marker=marker, color=colour, lw=1.8, ms=6)
                if m in PAPER_ROW:
                    v = paper.TABLE2[PAPER_ROW[m]][0 if key == "mAA_R" else 1]
                    ax.plot([1000], [v], marker="x", color=colour, ms=10, mew=2.2, ls="none")
                if ax is axes[0] and (len(d) or m in PAPER_ROW):
                    handles.append(Line2D([], [], marker=marker, color=colour, lw=1.8, ms=6,
                                          label=label + ("" if len(d) else " (paper only)")))
            ax.set_xscale("log")
            ax.set_xlim(8, 1300)
            ax.set_xticks([10, 25, 50, 100, 250, 500, 1000])
            ax.set_xticklabels(["10", "25", "50", "100", "250", "500", "1k"])
            ax.set_xlabel("iterations (hypotheses per pair, log scale)")
            ax.set_title(f"mAA@10° of {what}")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].set_ylabel("mAA@10° (fraction of pairs, 0-1)")
        handles.append(Line2D([], [], marker="x", color="k", ls="none", ms=9, mew=2.2,
                              label="paper at 1k iterations (Table 2), method colour"))
        fig.legend(handles=handles, loc="lower center", ncol=4, bbox_to_anchor=(0.5, -0.1), frameon=False)
        data = sorted(set(df["data"].dropna().astype(str))) if "data" in df else []
        note = "" if len(df) else " (no evaluation results yet: paper crosses only)"
        fig.suptitle("Fundamental matrix estimation: mAA@10° vs iterations"
                     + (f" on {', '.join(Path(p).name for p in data)}" if data else "") + note)
        fig.tight_layout()
        return _save(fig, out_dir, "fundamental_iterations"), note.strip(" ()")


# ---------------------------------------------------------------------------------- line steps


def _draw_line(ax, line, size: float, **kw) -> None:
    a, b, c = (float(v) for v in line)
    p0 = -c * np.array([a, b])
    d = np.array([-b, a])
    t = np.array([-3 * size, 3 * size]) + float(np.dot(np.array([size / 2, size / 2]) - p0, d))
    pts = p0[None] + t[:, None] * d[None]
    ax.plot(pts[:, 0], pts[:, 1], **kw)


def line_setup(o: dict[str, Any]) -> dict[str, Any]:
    """The line figure's inputs, read and checked before ``plot`` starts its MLflow run: the data file (a missing
    one regenerated as dvc.lock records it), the policy, and an explicit ``line_index`` in range and usable."""
    from rlsac.data import lines, validity
    from rlsac.reports.provenance import recorded_lines

    notes = []
    path = Path(o["line_data"])
    with recorded_lines(path) as readable:
        data, attrs = lines.read(readable)
    if readable != path:
        notes.append(f"{path} regenerated as recorded in dvc.lock")
    actor, task, psi, why = _load_policy(o["line_checkpoint"], "line", o["device"])
    if why:
        notes.append(why)
    report, n = attrs.get(validity.REPORT), len(data["points"])
    index = None if o["line_index"] == "auto" else \
        validity.row_position(report, int(o["line_index"]), n, path, "line_index")
    return {"path": path, "data": data, "attrs": attrs, "rows": validity.kept_rows(report, n), "actor": actor,
            "task": task, "psi": psi, "notes": notes, "index": index}


def plot_line_steps(o: dict[str, Any], out_dir: Path, setup: dict[str, Any] | None = None) -> tuple[list[str], str]:
    from rlsac.data import lines
    from rlsac.maths import metrics

    su = setup or line_setup(o)
    path, data, attrs, actor, task, psi = su["path"], su["data"], su["attrs"], su["actor"], su["task"], su["psi"]
    notes = list(su["notes"])
    rate = float(attrs.get("outlier_rate", float("nan")))
    source = f"{path.name} (seed {attrs['seed']})" if "seed" in attrs else path.name
    size = float(attrs.get("picture_size", 10.0))
    n = len(data["points"])
    if su["index"] is None:
        cand = min(n, 64)
        batch = lines.to_batch(data, slice(0, cand))
        steps = _episode(task, batch, actor, psi, int(o["seed"]))
        err = np.stack([metrics.line_angle_deg(s["hyp"].numpy()[:, :2], batch["line"][:, :2]) for s in steps], 1)
        score = np.where(err[:, -1] < 0.5, err[:, 0] - err[:, -1], -np.inf)
        idx = int(np.argmax(score)) if np.isfinite(score).any() else 0
        pick = f"#{su['rows'][idx]} (auto: largest error drop of the first {cand} instances)"
        steps = [{k: v[idx: idx + 1] for k, v in s.items()} for s in steps]
    else:
        idx = su["index"]
        batch = lines.to_batch(data, slice(idx, idx + 1))
        steps = _episode(task, batch, actor, psi, int(o["seed"]))
        pick = f"#{su['rows'][idx]}"
    pts, gt = data["points"][idx], data["line"][idx]
    shown = _pick_steps(len(steps), o["line_steps"])
    rows, cols = _grid(len(shown))
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(rows, cols, figsize=(4.3 * cols, 4.5 * rows + 0.8), squeeze=False)
        for ax in axes.flat[len(shown):]:
            ax.axis("off")
        for ax, t in zip(axes.flat, shown, strict=False):
            s = steps[t]
            hyp, inl, ms = s["hyp"][0].numpy(), s["inliers"][0].numpy(), s["minimal_set"][0].numpy()
            err = float(metrics.line_angle_deg(hyp[None, :2], gt[None, :2])[0])
            ax.scatter(pts[~inl, 0], pts[~inl, 1], s=18, c="tab:red", alpha=0.85, lw=0, zorder=4)
            ax.scatter(pts[inl, 0], pts[inl, 1], s=22, c="tab:green", lw=0, zorder=4)
            ax.scatter(pts[ms, 0], pts[ms, 1], s=70, facecolors=np.where(inl[ms][:, None], [[0.17, 0.63, 0.17]],
                                                                          [[0.84, 0.15, 0.16]]),
                       edgecolors="black", linewidths=2, zorder=5)
            _draw_line(ax, gt, size, color="gold", lw=3, alpha=0.8, zorder=1)
            _draw_line(ax, hyp, size, color="tab:blue", lw=1.4, zorder=2)
            for sign in (-1, 1):
                band = hyp.copy()
                band[2] += sign * task.threshold
                _draw_line(ax, band, size, color="tab:blue", lw=0.9, ls="--", zorder=2)
            ax.set_xlim(0, size)
            ax.set_ylim(0, size)
            ax.set_aspect("equal")
            ax.set_title(f"step {t + 1}: inlier ratio {inl.mean():.2f}, error {err:.2f}°")
            ax.set_xlabel("x (picture units)")
            ax.set_ylabel("y (picture units)")
        handles = [
            Line2D([], [], marker="o", color="tab:green", ls="none", label="inlier of the hypothesis"),
            Line2D([], [], marker="o", color="tab:red", ls="none", label="outlier"),
            Line2D([], [], marker="o", mfc="white", mec="black", mew=2, ms=9, ls="none", label="minimal set"),
            Line2D([], [], color="gold", lw=3, label="ground truth"),
            Line2D([], [], color="tab:blue", lw=1.6, label="hypothesis"),
            Line2D([], [], color="tab:blue", lw=0.9, ls="--", label=f"threshold ±{task.threshold:g}"),
        ]
        fig.legend(handles=handles, loc="lower center", ncol=6, frameon=False, bbox_to_anchor=(0.5, -0.01))
        who = f"RLSAC policy {Path(o['line_checkpoint']).name}" if actor is not None else \
            "NO CHECKPOINT: uniform random minimal sets (RANSAC)"
        fig.suptitle(f"2D line fitting, outlier rate {rate:g}, instance {pick} of {source}\n"
                     f"{who}, one episode of {len(steps)} steps (max sampling)")
        fig.tight_layout(rect=(0, 0.04, 1, 1))
        return _save(fig, out_dir, "line_steps"), "; ".join(notes)


# -------------------------------------------------------------------------------- fundamental


def _image_root(attrs: dict, data_path: Path, image_root: str | None) -> Path:
    """``image_root``, else the prepared file's attrs root/split: as given (relative to the working
    directory), or relative to an ancestor of the data file (the repository it was prepared in)."""
    if image_root:
        return Path(image_root)
    root = Path(str(attrs.get("root", "data/raw/strecha"))) / str(attrs.get("split", "all"))
    if root.is_absolute() or root.is_dir():
        return root
    for parent in data_path.resolve().parents:
        if (parent / root).is_dir():
            return parent / root
    return root


def _pair_images(data: dict, root: Path, i: int):
    """-> ((img1, found), (img2, found)) RGB arrays (a grey canvas when missing), and the paths tried."""
    import cv2

    scene, pair = str(data["scene"][i]), str(data["pair"][i])
    ids = pair.split("-")
    out, paths = [], []
    for k, im_id in enumerate(ids[:2]):
        p = root / scene / "images" / f"{im_id}.jpg"
        paths.append(str(p))
        img = cv2.imread(str(p)) if p.is_file() else None
        if img is None:
            w, h = (int(v) for v in data[f"size{k + 1}"][i])
            img = np.full((h, w, 3), 235, np.uint8)
            out.append((img, False))
        else:
            out.append((img[..., ::-1], True))
    return out, paths


def _canvas(images, data: dict, i: int, gap: int = 12):
    """Side-by-side canvas and the per-image coordinate transforms (scale, x offset)."""
    (im1, _), (im2, _) = images
    h = max(im1.shape[0], im2.shape[0])
    canvas = np.full((h, im1.shape[1] + gap + im2.shape[1], 3), 255, np.uint8)
    canvas[: im1.shape[0], : im1.shape[1]] = im1
    canvas[: im2.shape[0], im1.shape[1] + gap:] = im2
    s1 = np.array([im1.shape[1], im1.shape[0]]) / np.maximum(np.asarray(data["size1"][i], float), 1)
    s2 = np.array([im2.shape[1], im2.shape[0]]) / np.maximum(np.asarray(data["size2"][i], float), 1)
    return canvas, (s1, 0.0), (s2, float(im1.shape[1] + gap))


def _draw_pair(ax, canvas, tf1, tf2, coords, inliers, minimal, lw_scale: float = 1.0) -> None:
    ax.imshow(canvas)
    x1 = coords[:, :2] * tf1[0]
    x2 = coords[:, 2:4] * tf2[0] + np.array([tf2[1], 0.0])
    for j in np.flatnonzero(inliers):
        ax.plot([x1[j, 0], x2[j, 0]], [x1[j, 1], x2[j, 1]], color="lime", lw=0.7 * lw_scale, alpha=0.75)
    for j in minimal:
        ax.plot([x1[j, 0], x2[j, 0]], [x1[j, 1], x2[j, 1]], color="blue", lw=1.8 * lw_scale, alpha=0.95)
        ax.plot([x1[j, 0], x2[j, 0]], [x1[j, 1], x2[j, 1]], "o", color="blue", ms=3.5 * lw_scale)
    ax.set_xticks([])
    ax.set_yticks([])


def _pose_errors(task, hyp, valid, inliers, batch) -> tuple[float, float]:
    from rlsac.tasks import as_numpy

    np_batch = {k: as_numpy(v) for k, v in batch.items()}
    e = task.errors(as_numpy(hyp), as_numpy(valid), as_numpy(inliers), np_batch)
    return float(e["err_R"][0]), float(e["err_t"][0])


def _err_text(eR: float, et: float) -> str:
    from rlsac.tasks.fundamental import MAX_ERR_R, MAX_ERR_T

    if eR >= MAX_ERR_R and et >= MAX_ERR_T:
        return "no pose (too few inliers or degenerate F)"
    return f"ε_R = {eR:.2f}°, ε_t = {et:.2f}°"


def _fundamental_setup(o: dict[str, Any]):
    """The two pair figures' inputs, read and checked before ``plot`` starts its MLflow run: the prepared file, the
    pair (``pair``: a row of the file, in range and usable), the policy and both images."""
    from rlsac.data import fundamental, validity

    path = Path(o["fundamental_data"])
    if not path.is_file():
        raise RlsacError(_missing_fundamental(path))
    data, attrs = fundamental.read(path)
    report, n = attrs.get(validity.REPORT), len(data["pair"])
    if o["pair"] == "auto":
        rate = fundamental.gt_inliers(data, 2.0).sum(1) / data["mask"].sum(1)
        i = int(np.argmin(np.abs(rate - 0.5)))
        how = f", auto-picked: ground-truth inlier rate {rate[i]:.2f}"
    else:
        i, how = validity.row_position(report, int(o["pair"]), n, path, "pair"), ""
    row = int(validity.kept_rows(report, n)[i])
    data["label"] = f"{data['scene'][i]} {data['pair'][i]} (#{row} of {path.name}{how})"
    batch = fundamental.to_batch(data, [i])
    actor, task, psi, why = _load_policy(o["fundamental_checkpoint"], "fundamental", o["device"])
    images, paths = _pair_images(data, _image_root(attrs, path, o["image_root"]), i)
    notes = [why] if why else []
    if not all(ok for _, ok in images):
        raise RlsacError(f"images of pair {data['label']} not found ({', '.join(paths)}); option image_root "
                         "gives the folder holding <scene>/images/")
    return data, attrs, i, batch, actor, task, psi, images, notes


def _missing_fundamental(path: Path) -> str:
    from rlsac.reports.provenance import lock_stage

    hit = lock_stage(path)
    how = f"`dvc repro {hit[0]}`" if hit else "`rlsac import-scenes` then `rlsac prepare-cvpr2020`"
    return f"{path}: no prepared two-view file (option fundamental_data); make it with {how}"


def check_inputs(o: dict[str, Any]) -> list[str]:
    """Problems that would stop the requested figures, found before anything is drawn (cheap checks only)."""
    from rlsac.reports.provenance import lock_stage

    problems = []
    if "fundamental_iterations" in o["which"] and o["iterations_csv"] and not Path(o["iterations_csv"]).is_file():
        problems.append(f"{o['iterations_csv']}: no such iterations CSV")
    if "folds_iterations" in o["which"] and not Path(o["folds_iterations_csv"]).is_file():
        problems.append(f"{o['folds_iterations_csv']}: no such file (rlsac table --which folds)")
    if "essential_iterations" in o["which"] and not Path(o["essential_iterations_csv"]).is_file():
        problems.append(f"{o['essential_iterations_csv']}: no such file (rlsac table --which essential)")
    if "learning_curves" in o["which"] and not list(Path(o["folds_checkpoints"]).glob("*/*/*.pt")):
        problems.append(f"{o['folds_checkpoints']}: no fold checkpoints (rlsac folds --stage train)")
    if "line_steps" in o["which"]:
        if not Path(o["line_data"]).is_file() and lock_stage(o["line_data"]) is None:
            problems.append(f"{o['line_data']}: no such line file, and dvc.lock records no stage that makes it")
        if o["line_checkpoint"] and not Path(o["line_checkpoint"]).is_file():
            problems.append(f"{o['line_checkpoint']}: no such checkpoint")
    if {"fundamental_pair", "fundamental_steps"} & set(o["which"]):
        if not Path(o["fundamental_data"]).is_file():
            problems.append(_missing_fundamental(Path(o["fundamental_data"])))
        if o["fundamental_checkpoint"] and not Path(o["fundamental_checkpoint"]).is_file():
            problems.append(f"{o['fundamental_checkpoint']}: no such checkpoint")
    return problems


def plot_fundamental_pair(o: dict[str, Any], out_dir: Path, setup: tuple | None = None) -> tuple[list[str], str]:
    data, attrs, i, batch, actor, task, psi, images, notes = setup or _fundamental_setup(o)
    iters = int(o["fundamental_iterations"])
    if actor is not None:
        out = _rlsac_rollout(task, batch, actor, psi, int(o["seed"]), iters)
        counts = torch.stack([s["count"] for s in out["steps"]])  # (T, R): first maximum = the env's best
        t, r = divmod(int(torch.argmax(counts.flatten())), counts.shape[1])
        minimal = out["steps"][t]["minimal_set"][r].numpy()
        who = f"RLSAC ({Path(o['fundamental_checkpoint']).name}), {iters} iterations"
    else:
        from rlsac.estimation.baselines import finalize
        from rlsac.estimation.lo import score_sets
        from rlsac.estimation.sampling import gather_points, uniform_minimal_sets

        # plain RANSAC written out, so that the minimal set shown is the one behind the estimate
        gen = torch.Generator().manual_seed(int(o["seed"]))
        idx = uniform_minimal_sets(batch["mask"], task.sample_size, iters, gen)[0]  # (iters, m)
        hyps, valid, _, cnt = score_sets(task, gather_points(batch["coords"], idx[None]), batch["coords"],
                                         batch["mask"])
        hyps, cnt = hyps[0], cnt[0].masked_fill(~valid[0], -1)
        best = int(cnt.argmax())
        minimal = idx[best].numpy()
        out = finalize(task, batch["coords"], batch["mask"], hyps[best: best + 1],
                       torch.as_tensor([bool(cnt[best] >= task.sample_size)]))
        who = f"NO CHECKPOINT: RANSAC fallback (ours), {iters} iterations"
    inl = out["inliers"][0].cpu().numpy().astype(bool)
    n_valid = int(batch["mask"][0].sum())
    eR, et = _pose_errors(task, out["hyp"], out["valid"], out["inliers"], batch)
    canvas, tf1, tf2 = _canvas(images, data, i)
    with plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(14, 14 * canvas.shape[0] / canvas.shape[1] + 1.0))
        _draw_pair(ax, canvas, tf1, tf2, batch["coords"][0].numpy(), inl, minimal)
        ax.set_title(f"{data['label']}: inlier rate {inl.sum() / n_valid:.2f} "
                     f"({inl.sum()}/{n_valid}), {_err_text(eR, et)}\n{who}")
        residual = RESIDUAL_LABEL.get(task.residual, task.residual)
        handles = [Line2D([], [], color="blue", lw=2, label="minimal set (best hypothesis)"),
                   Line2D([], [], color="lime", lw=1.5, label=f"inliers ({residual} ≤ {task.threshold:g})")]
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=2, frameon=False)
        fig.tight_layout()
        return _save(fig, out_dir, "fundamental_pair"), "; ".join(notes)


def plot_fundamental_steps(o: dict[str, Any], out_dir: Path, setup: tuple | None = None) -> tuple[list[str], str]:
    data, attrs, i, batch, actor, task, psi, images, notes = setup or _fundamental_setup(o)
    steps = _episode(task, batch, actor, psi, int(o["seed"]))
    shown = _pick_steps(len(steps), o["fundamental_steps"])
    canvas, tf1, tf2 = _canvas(images, data, i)
    cols = 2 if len(shown) > 1 else 1
    rows = math.ceil(len(shown) / cols)
    n_valid = int(batch["mask"][0].sum())
    with plt.rc_context(STYLE):
        w = 8.0
        fig, axes = plt.subplots(rows, cols, figsize=(w * cols, rows * (w * canvas.shape[0] / canvas.shape[1] + 0.7)
                                                      + 1.0), squeeze=False)
        for ax in axes.flat[len(shown):]:
            ax.axis("off")
        for ax, t in zip(axes.flat, shown, strict=False):
            s = steps[t]
            inl = s["inliers"][0].numpy().astype(bool)
            valid = torch.as_tensor([bool(s["count"][0] >= task.sample_size)])
            eR, et = _pose_errors(task, s["hyp"], valid, s["inliers"], batch)
            _draw_pair(ax, canvas, tf1, tf2, batch["coords"][0].numpy(), inl, s["minimal_set"][0].numpy(), 0.8)
            ax.set_title(f"step {t + 1}: inlier rate {inl.sum() / n_valid:.2f}, {_err_text(eR, et)}")
        who = f"RLSAC policy {Path(o['fundamental_checkpoint']).name}" if actor is not None else \
            "NO CHECKPOINT: uniform random minimal sets (RANSAC)"
        handles = [Line2D([], [], color="blue", lw=2, label="minimal set of the step"),
                   Line2D([], [], color="lime", lw=1.5, label="inliers of its hypothesis (unrefined)")]
        fig.legend(handles=handles, loc="lower center", ncol=2, frameon=False, bbox_to_anchor=(0.5, 0.0))
        fig.suptitle(f"{data['label']}\none episode of {len(steps)} steps: {who}")
        fig.tight_layout(rect=(0, 0.03, 1, 1))
        return _save(fig, out_dir, "fundamental_steps"), "; ".join(notes)


# ------------------------------------------------------------------------------------------ entry


def read_inputs(o: dict[str, Any]) -> dict[str, Any]:
    """Every input of the requested figures read and checked, before ``plot`` starts its MLflow run (issue #28,
    item 2: a corrupt h5 file or checkpoint, or an index out of range, failed inside the run): the CSVs parsed,
    the checkpoints loaded, the data files read and validated, the indices checked, the images found.
    -> {figure name (or "fundamental" for the two pair figures): what its drawing function takes}"""
    from rlsac.reports import fold_figures

    out: dict[str, Any] = {}
    which = set(o["which"])
    if "fundamental_iterations" in which:
        if o["iterations_csv"]:
            from rlsac.evaluation.results import read_table

            out["fundamental_iterations"] = read_table(o["iterations_csv"], ("iterations", "mAA_R", "mAA_t"),
                                                       "iterations CSV")
            if out["fundamental_iterations"] is None:
                raise RlsacError(f"{o['iterations_csv']}: no such file")
        else:
            from rlsac.reports.tables import iterations_csv

            with tempfile.TemporaryDirectory() as tmp:  # rebuilt from the summaries, not written over reports/
                out["fundamental_iterations"] = iterations_csv(o["eval_root"], tmp)
    for name in ("folds_iterations", "essential_iterations"):
        if name in which:
            out[name] = fold_figures.read_iterations(o[f"{name}_csv"], name)
    if "learning_curves" in which:
        out["learning_curves"] = fold_figures.read_checkpoints(o["folds_checkpoints"])
    if "line_steps" in which:
        out["line_steps"] = line_setup(o)
    if which & {"fundamental_pair", "fundamental_steps"}:
        out["fundamental"] = _fundamental_setup(o)
    return out


def plot(options: dict[str, Any], track: bool = True) -> dict[str, Any]:
    """Draw the requested figures -> {"figures": comma list of files, "notes": what was regenerated, "run_id"}."""
    from rlsac.tracking import start_run

    o = _options(options)
    out_dir = Path(o["out_dir"])
    problems = check_inputs(o)
    if problems:
        raise RlsacError("rlsac plot needs: " + "; ".join(problems)
                         + " (`--set which=...` draws only some figures; nothing was written)")
    from rlsac.io import check_writable
    from rlsac.tracking import check_store

    check_writable(out_dir, "figure folder", folder=True)  # an existing file there: refused now, not after drawing
    check_store(track, "figures")
    inputs = read_inputs(o)
    files: list[str] = []
    notes: list[str] = []
    with start_run("figures", "plot " + ",".join(o["which"]), params=o, tags={"command": "plot"},
                   enabled=track) as run:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f".{out_dir.name}-", dir=out_dir.parent) as tmp:
            drawn: list[str] = []  # every figure first, into tmp; out_dir is touched only when all succeeded
            for name in o["which"]:
                if name == "fundamental_iterations":
                    paths, note = plot_iterations(inputs[name], Path(tmp))
                elif name in ("folds_iterations", "essential_iterations"):
                    from rlsac.reports import fold_figures

                    paths, note = fold_figures.plot_folds_iterations(inputs[name], Path(tmp), name)
                elif name == "learning_curves":
                    from rlsac.reports import fold_figures

                    paths, note = fold_figures.plot_learning_curves(inputs[name], Path(tmp))
                elif name == "line_steps":
                    paths, note = plot_line_steps(o, Path(tmp), inputs[name])
                elif name == "fundamental_pair":
                    paths, note = plot_fundamental_pair(o, Path(tmp), inputs["fundamental"])
                else:
                    paths, note = plot_fundamental_steps(o, Path(tmp), inputs["fundamental"])
                drawn += paths
                if note:
                    notes.append(f"{name}: {note}")
            out_dir.mkdir(parents=True, exist_ok=True)
            for p in drawn:
                final = out_dir / Path(p).name
                os.replace(p, final)
                files.append(str(final))
        for p in files:
            run.artifact(p, "figures")
        if notes:
            run.tags({"notes": " | ".join(notes)[:4000]})
    for n in notes:
        print(f"note: {n}")
    return {"figures": ", ".join(files), "notes": " | ".join(notes) or "none", "run_id": run.run_id}
