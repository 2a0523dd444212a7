"""Evaluate one method on one data file: per-instance errors CSV, summary JSON, one MLflow run.

``evaluate(options)`` is what ``rlsac evaluate`` calls, with one ``EvalOptions`` built and checked at the command
line's edge (``check_options``; a mapping is checked into one the same way) and read by attribute down to the
method's estimator. Its fields (all but ``task``/``method``/``data`` have defaults):

    task        a registered task (rlsac.tasks.TASKS: line, fundamental, essential)
    method      a registered method (rlsac.evaluation.methods.METHODS: ransac, rlsac, uniform, guided, oracle, OpenCV's
                opencv_ransac | usac | usac_accurate | magsac | prosac, the *-lo variants); each says which
                task capability it needs, checked here before any work
    data        h5 file written by ``rlsac synth-lines`` / ``rlsac prepare-cvpr2020``
    checkpoint  trained checkpoint (.pt): methods rlsac(-lo) (RLSAC's), ngransac(-lo) (NG-RANSAC's, rlsac.rl.ngransac)
    iterations  hypotheses per instance (default 150 for lines, 1000 for fundamental)
    steps_per_episode  RLSAC only; default: the checkpoint's value, else 15
    seed, device ("auto" | "cpu" | "cuda"), batch_size, out_dir (default reports/eval/<name>)
    threads     torch CPU threads while the method runs (default 1, see THREADS; 0 = leave torch's setting)
    sampling    RLSAC test-time sampling, "max" (paper) or "prob"; tags: extra MLflow run tags (dict)

The random stream is one seeded ``torch.Generator`` consumed batch after batch, so results are
reproducible for a given (seed, batch_size, device).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd
import torch

from rlsac.config import SEED_RANGE, check_value
from rlsac.data import n_unusable, validity
from rlsac.devices import device_name as resolve_device  # noqa: F401  (also rlsac.evaluation.evaluate.resolve_device)
from rlsac.errors import RlsacError
from rlsac.evaluation.methods import METHODS
from rlsac.io import atomic_path, check_writable, write_json
from rlsac.progress import tqdm  # no bars unless a person watches (not under CI, not redirected)
from rlsac.tasks import (  # noqa: F401
    TASKS,
    Task,
    opencv_threshold,
    prefiltered,
    task_class,
    task_for,
    task_from,
)
from rlsac.tasks.registry import as_numpy as _np
from rlsac.tracking import check_store, start_run

# torch CPU threads for the evaluation loop. One thread: per-step tensors are small (one instance, or
# chunks of 4096 points), so a second thread mostly adds synchronisation, and on a shared machine it
# competes with the other jobs. Measured on the 2-core machine, one vs two threads: issue #17, RLSAC
# 2-8x and our RANSAC 3-5x faster with one; benchmarks/line_rollout.py (32 line instances per call,
# wall time, machine loaded by other jobs): RLSAC 78 vs 677 ms/instance, our RANSAC 1.4 vs 3.9 ms.
THREADS = 1
@dataclass(frozen=True)
class EvalOptions:
    """One evaluation's options: built and checked once (``check_options``: by ``rlsac evaluate`` at the command
    line's edge, and by every command that runs evaluations before its first one), then read by attribute down to the
    method's estimator (rlsac.evaluation.methods, rlsac.tasks.task_for). Its fields are what config.json and the MLflow
    run record (``recorded_options``)."""

    task: str  # a registered task (rlsac.tasks.TASKS)
    method: str  # a registered method (rlsac.evaluation.methods.METHODS)
    data: str  # the h5 file
    checkpoint: str | None = None
    iterations: int | None = None  # None: the task's default_iterations (check_options fills it)
    steps_per_episode: int | None = None
    seed: int = 0
    device: str = "auto"
    batch_size: int = 256
    out_dir: str | None = None  # None: reports/eval/<run_name> (check_options fills it)
    sampling: str = "max"  # RLSAC test-time sampling: max (paper) or prob (ablation)
    # extra MLflow run tags, e.g. {"ablation": "sampling", "variant": "full"} (rlsac.experiments.ablate)
    tags: dict | None = None
    threads: int | None = None  # None = THREADS
    # guided: minimal sets drawn with probabilities ~ exp(-SNN / guide_temperature) in the RLSAC environment, a
    # hand-made sampler that uses the same side information as the policy (not in the paper). 0.1: the middle of
    # the tuning grid; the fold benchmark tunes T per fold on validation pairs (rlsac.evaluation.tune)
    guide_temperature: float = 0.1
    # *-lo methods: rlsac.estimation.lo.LOConf options (params.yaml evaluate.<task>.lo); ignored by others
    lo: dict | None = None
    # RLSAC: recompute the policy's logits every this many steps (1 = every step, the paper; a speed lever of
    # issue #17 that changes the algorithm: reports/speed.md)
    policy_every: int = 1
    # RLSAC and its uniform / guided controls (the environment; not in the paper, issue #17 speed levers,
    # reports/speed.md): minimal sets drawn and scored per episode step (1 = the paper), and the confidence of
    # RANSAC's termination bound at which an instance stops before its budget (0 = never, the paper)
    sets_per_step: int = 1
    confidence: float = 0.0
    # the two settings the CVPR 2020 tutorial tunes per method on validation (rlsac.evaluation.tune; None = off): the
    # inlier threshold in pixels for every method (ours: the task's residual unit, OpenCV: its threshold), and the SNN
    # pre-filter, matches whose SNN ratio is above it are dropped before the method sees the pair
    threshold_px: float | None = None
    prefilter: float | None = None
    # our samplers' final refit on the inliers (None = the task's ``refit_output``); tuned on validation for Table E
    refit_output: bool | None = None

    def replace(self, **changes) -> EvalOptions:
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """Every field by name, in declaration order (shallow: ``lo`` and ``tags`` are the object's own)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


REQUIRED = ("task", "method", "data")
# the options with defaults, as a params.yaml evaluate.<task> section may set them (check_params) and tuning varies them
DEFAULTS: dict[str, Any] = {f.name: f.default for f in fields(EvalOptions) if f.name not in REQUIRED}
# sets_per_step's fixed cap (the data bound it further: check_sets_per_step). One step draws (R, 2k, N) random
# numbers and remembers R k sets: 1024 keeps that near 200 MB for a batch of 256 line instances; the measured
# levers used 8 and 12 (reports/speed.md). 10^9 used to allocate until the process died.
MAX_SETS_PER_STEP = 1024
# the options above that a params.yaml evaluate.<task> section passes on to every environment method's run
SAMPLER_OPTIONS = ("sets_per_step", "confidence")
# the RLSAC environment's options and the methods that read them: another method given a value other than the default
# is refused (issue #49: NG-RANSAC's config.json recorded a --sets-per-step it ignored); the default stays recorded
READ_BY = {"policy_every": ("rlsac",), "sets_per_step": ("rlsac", "uniform", "guided")}
# ... and those of them not recorded at all for a method (config.json and the MLflow run hold only the options the
# method used; issue #49): NG-RANSAC draws its sets from its own network, never in the RLSAC environment. The other
# methods outside READ_BY (our RANSAC, OpenCV's, the peers) still record the defaults their committed results hold
NOT_RECORDED = {"ngransac": ("sets_per_step", "policy_every")}
# what evaluate measures of time: written to TIMING_FILE beside summary.json (git- and dvc-ignored) and to MLflow
TIMING_FILE = "timing.json"
TIMING_KEYS = ("seconds", "seconds_per_instance", "lo_seconds_per_instance", "lo_time_fraction")


# types and ranges of the options a params.yaml evaluate.<task> section may set (``check_params``)
TYPES = {"checkpoint": str, "iterations": int, "steps_per_episode": int, "seed": int, "device": str,
         "batch_size": int, "out_dir": str, "sampling": str, "tags": dict, "threads": int, "guide_temperature": float,
         "lo": dict, "policy_every": int, "sets_per_step": int, "confidence": float, "threshold_px": float,
         "prefilter": float, "refit_output": bool}
# threshold_px: below a thousandth of a pixel is below any keypoint's precision, above 1000 px every match of a
# Strecha image (3072 px wide) is an inlier (issue #64: 1e300 and 1e-300 "succeeded" with mAA 0)
RANGES = {"iterations": "[1, inf)", "steps_per_episode": "[1, inf)", "seed": SEED_RANGE,
          "device": ("auto", "cpu", "cuda"), "batch_size": "[1, inf)", "sampling": ("max", "prob"),
          "threads": "[0, inf)", "guide_temperature": "(0, inf)", "policy_every": "[1, inf)",
          "sets_per_step": f"[1, {MAX_SETS_PER_STEP}]", "confidence": "[0, 1)", "threshold_px": "[0.001, 1000]",
          "prefilter": "(0, 1]"}


def check_params(params: dict[str, Any]) -> None:
    """params.yaml ``evaluate``: per registered task, evaluate options typed and ranged, its ``lo`` an LOConf
    whatever method runs later (issue #28, item 3: LO options were checked only by the *-lo methods)."""
    from rlsac.config import check_mapping, section
    from rlsac.estimation.lo import lo_conf

    for task in section(params, "evaluate"):
        task_class(task)
        where = f"evaluate.{task}"
        given = check_mapping(section(params, "evaluate", task), DEFAULTS, where, TYPES, RANGES)
        if given.get("lo") is not None:
            lo_conf(given["lo"], f"{where}.lo")


def sampler_options(section: dict[str, Any]) -> dict[str, Any]:
    """The ``SAMPLER_OPTIONS`` present in a params.yaml evaluate.<task> section."""
    return {k: section[k] for k in SAMPLER_OPTIONS if k in section}


def check_options(options: dict[str, Any] | EvalOptions, checkpoint_later: bool = False) -> EvalOptions:
    """Fill defaults and validate -> the evaluation's ``EvalOptions`` (a mapping of options, or an ``EvalOptions`` to
    check again). ``checkpoint_later``: the checkpoint may not exist yet (a command that trains it first)."""
    if isinstance(options, EvalOptions):
        options = options.as_dict()
    missing = [k for k in REQUIRED if not options.get(k)]
    if missing:
        raise RlsacError(f"evaluate needs {', '.join(missing)}")
    unknown = sorted(set(options) - set(DEFAULTS) - set(REQUIRED))
    if unknown:
        raise RlsacError(f"unknown evaluate option(s) {unknown}")
    o = {**DEFAULTS, **{k: v for k, v in options.items() if v is not None}}
    task_cls = task_class(o["task"])
    if o["method"] not in METHODS:
        raise RlsacError(f"unknown method '{o['method']}' (known: {', '.join(METHODS)})")
    method = METHODS[o["method"]]
    why = method.unsupported(task_cls, TASKS)
    if why:
        raise RlsacError(why)
    o["guide_temperature"] = _checked(o, "guide_temperature")
    if method.checkpoint and not o["checkpoint"]:
        raise RlsacError(f"method '{o['method']}' needs --checkpoint")
    if method.lo or o["lo"] is not None:  # bad LO options fail before any work, also where the method has no LO
        from rlsac.estimation.lo import lo_conf

        if o["lo"] is not None and not isinstance(o["lo"], dict):
            raise RlsacError(f"evaluate.lo must be a mapping of LO options, got {o['lo']!r}")
        lo_conf(o["lo"])
    if o["checkpoint"] and not method.checkpoint:  # it would only mislabel the run and its outputs
        raise RlsacError(f"--checkpoint is used by the trained methods only (rlsac, ngransac and their -lo), "
                         f"not by {o['method']}")
    if o["checkpoint"] and not Path(o["checkpoint"]).is_file() and not checkpoint_later:
        raise RlsacError(f"{o['checkpoint']}: no such checkpoint file")
    if o["iterations"] is None:
        o["iterations"] = task_cls.default_iterations
    o["threads"] = THREADS if o["threads"] is None else int(o["threads"])
    if o["threads"] < 0:
        raise RlsacError(f"threads must be >= 0, got {o['threads']}")
    for key in ("iterations", "batch_size"):
        o[key] = check_value(key, o[key], int)
        if o[key] <= 0:
            raise RlsacError(f"{key} must be positive, got {o[key]}")
    if o["steps_per_episode"] is not None:
        o["steps_per_episode"] = check_value("steps_per_episode", o["steps_per_episode"], int)
        if o["steps_per_episode"] <= 0:
            raise RlsacError(f"steps_per_episode must be positive, got {o['steps_per_episode']}")
    for key in ("seed", "sampling", "policy_every", "sets_per_step", "confidence"):
        o[key] = _checked(o, key)
    base = o["method"].removesuffix("-lo")
    for key, readers in READ_BY.items():  # config.json and MLflow record every option: none that was ignored
        if base not in readers and o[key] != DEFAULTS[key]:
            raise RlsacError(f"{key} {o[key]}: --method {o['method']} does not read it (only {', '.join(readers)} "
                             "and their -lo variants do)")
    if o["threshold_px"] is not None:
        o["threshold_px"] = _checked(o, "threshold_px")
        if not hasattr(task_cls, "px_thresholds"):
            raise RlsacError(f"task '{o['task']}' has no pixel threshold (threshold_px is for the two-view tasks)")
    if o["prefilter"] is not None:
        o["prefilter"] = _checked(o, "prefilter")
        if not hasattr(task_cls, "match_quality"):
            raise RlsacError(f"task '{o['task']}' has no match quality to pre-filter by")
    if not Path(o["data"]).is_file():
        raise RlsacError(f"{o['data']}: no such file")
    out = EvalOptions(**{**o, **{k: str(o[k]) for k in ("data", "checkpoint", "out_dir") if o[k] is not None}})
    return out if out.out_dir is not None else out.replace(out_dir=str(Path("reports") / "eval" / run_name(out)))


def _checked(o: dict[str, Any], key: str) -> Any:
    """Option ``key`` of ``o`` coerced to its type and range-checked (``TYPES``, ``RANGES``: the params.yaml
    section's checks too)."""
    return check_value(key, o[key], TYPES[key], RANGES[key])


def run_name(o: EvalOptions) -> str:
    model = f"_{Path(o.checkpoint).stem}" if o.checkpoint else ""
    return f"{o.task}_{o.method}{model}_{Path(o.data).stem}_i{o.iterations}_s{o.seed}"


def mlflow_name(o: EvalOptions) -> str:
    """The MLflow run's name: method, model, test-time sampling where not the paper's, the data file with its folders
    (fold and regime), budget and seed (``evaluate rlsac rlsac folds/hard/entry/test i1000 s0``; the sampling
    ablation's rows: ``evaluate rlsac rlsac prob ...``); ``run_name`` names the default output folder."""
    from rlsac.tracking import data_label

    model = f" {Path(o.checkpoint).stem}" if o.checkpoint else ""
    sampling = f" {o.sampling}" if o.method == "rlsac" and o.sampling != "max" else ""
    return f"evaluate {o.method}{model}{sampling} {data_label(o.data)} i{o.iterations} s{o.seed}"


def make_estimator(o: EvalOptions, device: str) -> tuple[Task, Callable[[dict, torch.Generator], dict], dict]:
    """-> (task, estimate(batch, generator) -> {hyp, valid, inliers} torch tensors, extra run params),
    built by the method's registered builder (rlsac.evaluation.methods)."""
    return METHODS[o.method].build(o, device, None)


def pair_seed(seed: int, scene: str, pair: str) -> int:
    """A pair's own random seed from (seed, scene, pair key): its result does not depend on the file's
    order or on the other pairs in it (a stable hash, unlike Python's salted ``hash``)."""
    digest = hashlib.sha256(f"{int(seed)}/{scene}/{pair}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & (2**63 - 1)


def run_method(task: Task, estimate: Callable, data: dict, to_batch: Callable, n: int, seed: int,
               device: str, batch_size: int, desc: str = "evaluate", prefilter: float | None = None
               ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Run ``estimate`` over ``n`` instances -> (per-instance errors, inlier counts); ``prefilter``: the SNN
    pre-filter (``prefiltered``) applied to every batch first.

    Named pairs (two-view data: ``scene`` and ``pair`` keys) run one at a time, each with the
    generator seeded by ``pair_seed``; synthetic instances run in batches of ``batch_size`` from one
    generator seeded by ``seed`` (reproducible for a given seed, batch size and device).
    """
    g = torch.Generator(device=device)
    g.manual_seed(int(seed))
    per_pair = "pair" in data and "scene" in data
    if per_pair:
        batch_size = 1
    errs: dict[str, list[np.ndarray]] = {}
    counts: list[np.ndarray] = []
    hyps: list[np.ndarray] = []
    with tqdm(total=n, desc=desc, unit="inst", disable=None, leave=False) as bar:
        for start in range(0, n, batch_size):
            idx = slice(start, min(start + batch_size, n))
            if per_pair:
                g.manual_seed(pair_seed(seed, data["scene"][start], data["pair"][start]))
            batch = prefiltered(task, to_batch(data, idx, device=device), prefilter)
            out = estimate(batch, g)
            hyp, valid, inliers = _np(out["hyp"]), _np(out["valid"]).astype(bool), _np(out["inliers"]).astype(bool)
            np_batch = {k: _np(v) for k, v in batch.items()}
            for k, v in task.errors(hyp, valid, inliers, np_batch).items():
                errs.setdefault(k, []).append(np.asarray(v, dtype=np.float64))
            counts.append(inliers.sum(-1))
            if "hypotheses" in out:
                hyps.append(np.broadcast_to(_np(out["hypotheses"]), (idx.stop - idx.start,)).astype(np.int64))
            bar.update(idx.stop - idx.start)
    out = {k: np.concatenate(v) for k, v in errs.items()}
    if hyps and len(hyps) == len(counts):  # minimal sets scored per instance (an oracle scores none)
        out["n_hypotheses"] = np.concatenate(hyps)
    return out, np.concatenate(counts)


def score(o: EvalOptions, data: dict, device: str) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Run the resolved options ``o`` (``check_options``) on ``data`` already read, nothing written or tracked
    -> (the task's summary of the errors, the per-instance errors): what tuning compares grid points by."""
    task, estimate, _ = make_estimator(o, device)
    n = _n_instances(data)
    errors, _ = run_method(task, estimate, data, task_class(o.task).to_batch, n, o.seed, device, o.batch_size,
                           desc=f"{o.method} {Path(o.data).name}", prefilter=o.prefilter)
    return summarize(task, errors), errors


def summarize(task: Task, errors: dict[str, np.ndarray]) -> dict[str, Any]:
    """The task's summary of the errors, plus the mean number of minimal sets scored per instance."""
    s = {k: _plain(v) for k, v in task.summarize(errors).items()}
    if "n_hypotheses" in errors:
        s["hypotheses_mean"] = float(np.mean(errors["n_hypotheses"]))
    return s


def _n_instances(data: dict) -> int:
    for v in data.values():
        if hasattr(v, "shape") and len(v.shape) > 0:
            return int(v.shape[0])
    raise RlsacError("data file holds no instances")


@dataclass
class Prepared:
    """What ``prepare`` found and built before an evaluation's MLflow run: everything ``run`` needs."""

    o: EvalOptions  # the checked options
    device: str
    data: dict  # the task reader's arrays (usable instances only)
    attrs: dict  # the data file's attributes (with the reader's report of unusable instances, if any)
    task: Task
    estimate: Callable[[dict, torch.Generator], dict]
    extra: dict  # the method's extra run params (steps_per_episode, lo, ...)

    @property
    def n(self) -> int:
        return _n_instances(self.data)

    @property
    def n_unusable(self) -> int:
        """Instances of the file the reader left out (rlsac.data.validity), 0 when none."""
        return n_unusable(self.attrs)


def prepare(options: dict[str, Any] | EvalOptions, track: bool = True, read: Callable | None = None) -> Prepared:
    """Every check of an evaluation, before its MLflow run and its first write: options, outputs, the tracking
    store, the data file (read and validated), the options the data bound, the method's estimator (its checkpoint
    loaded). ``read(task_cls, path) -> (arrays, attrs)``: a reader to use instead of the task's (a cache, when one
    command checks many evaluations of one file: ``check_all``)."""
    o = options if isinstance(options, EvalOptions) else check_options(options)  # checked once
    task_cls = task_class(o.task)
    check_outputs(o)  # before any work: an unwritable output fails now, not at the end
    check_store(track, task_cls.experiment)
    device = resolve_device(o.device)
    data, attrs = (read or _read)(task_cls, o.data)
    if _n_instances(data) == 0:
        raise RlsacError(f"{o.data}: no instances")
    check_sets_per_step(o, data, task_cls)
    task, estimate, extra = make_estimator(o, device)
    check_prefilter(o, data, task_cls, task)
    return Prepared(o, device, data, attrs, task, estimate, extra)


def check_prefilter(o: EvalOptions, data: dict, task_cls, task: Task) -> None:
    """A pre-filter must leave some instance a minimal set (issue #64: --prefilter 1e-9 kept no point and scored
    every pair as a failure at exit 0). An instance it leaves short is scored as it comes, as the tables do."""
    if o.prefilter is None:
        return
    batch = task_cls.to_batch(data, slice(0, _n_instances(data)))
    most = int(prefiltered(task, batch, o.prefilter)["mask"].sum(-1).max())
    if most < task.sample_size:
        raise RlsacError(f"prefilter {o.prefilter:g} leaves fewer than a minimal set ({task.sample_size} points) "
                         f"in every instance of {o.data} (at most {most}): nothing could be estimated")


def check_all(options: list[dict[str, Any] | EvalOptions], track: bool = True,
              built_later: set[str] = frozenset()) -> None:
    """``prepare`` every evaluation of a command that runs several (rlsac folds, rlsac ablate) before the first
    one starts, so that a bad data file, checkpoint or option of the last fails before the first writes anything.
    Each data file is read once. ``built_later``: checkpoints the command trains before evaluating (not loaded)."""
    cache: dict[tuple[str, str], tuple[dict, dict]] = {}

    def read(task_cls, path):
        key = (task_cls.name, str(path))
        if key not in cache:
            cache[key] = _read(task_cls, path)
        return cache[key]

    for opts in options:
        ckpt = opts.checkpoint if isinstance(opts, EvalOptions) else opts.get("checkpoint")
        if ckpt and str(ckpt) in built_later:  # all but the checkpoint's contents
            o = check_options(opts, checkpoint_later=True)
            check_outputs(o)
            check_sets_per_step(o, read(task_class(o.task), o.data)[0], task_class(o.task))
            continue
        prepare(opts, track, read)


def check_outputs(o: EvalOptions) -> None:
    """Every file an evaluation writes into ``o.out_dir`` can be written (RlsacError otherwise)."""
    for f in ("errors.csv", "summary.json", "config.json", TIMING_FILE):
        check_writable(Path(o.out_dir) / f)


def _read(task_cls, path) -> tuple[dict, dict]:
    return task_cls.read(path)


def check_sets_per_step(o: EvalOptions, data: dict, task_cls) -> None:
    """sets_per_step k within what the data allows: at most the number of distinct minimal sets of the instance
    with the fewest points, C(n, m) (the environment draws k distinct unused sets per step)."""
    k = o.sets_per_step
    if k == 1:
        return
    n_min = int(task_cls.to_batch(data, slice(0, _n_instances(data)))["mask"].sum(-1).min())
    m = int(task_cls.sample_size)  # a dataclass default: the class attribute
    distinct = math.comb(n_min, m)
    if k > distinct:
        raise RlsacError(f"sets_per_step {k} is more than the {distinct} distinct minimal sets of {m} points that "
                         f"the smallest instance of {o.data} has ({n_min} points)")


def evaluate(options: dict[str, Any] | EvalOptions, track: bool = True) -> dict[str, Any]:
    """Evaluate ``options.method`` on ``options.data`` (an ``EvalOptions``, or a mapping ``check_options`` makes one
    of); write CSV + JSON; -> the summary dict."""
    return run(prepare(options, track), track)


def run(p: Prepared, track: bool = True) -> dict[str, Any]:
    """The evaluation ``prepare`` checked: its MLflow run, the method over every usable instance, the outputs."""
    o, device, data, task, estimate, extra = p.o, p.device, p.data, p.task, p.estimate, p.extra
    task_cls = task_class(o.task)
    n = p.n
    out_dir = Path(o.out_dir)
    params = {**recorded_options(o), "device": device, "n_instances": n, **extra, "task_options": _task_options(task),
              "data_attrs": {k: _plain(v) for k, v in p.attrs.items()}}
    tags = {"command": "evaluate", "method": o.method, **{k: str(v) for k, v in (o.tags or {}).items()}}
    with start_run(task_cls.experiment, mlflow_name(o), params=params, tags=tags, enabled=track) as mlrun:
        torch_threads = torch.get_num_threads()
        if device == "cpu" and o.threads > 0:
            torch.set_num_threads(o.threads)
        try:
            t0 = time.perf_counter()
            errors, counts = run_method(task, estimate, data, task_cls.to_batch, n, o.seed, device, o.batch_size,
                                        desc=f"{o.method} {Path(o.data).name}", prefilter=o.prefilter)
            seconds = time.perf_counter() - t0
        finally:
            torch.set_num_threads(torch_threads)
        summary = summarize(task, errors)
        summary.update(task=o.task, method=o.method, iterations=o.iterations, data=str(o.data),
                       checkpoint=o.checkpoint, seed=o.seed, device=device, n_instances=n, **extra)
        if p.n_unusable:  # only then: a file without unusable instances keeps its summary's bytes
            summary["n_unusable"] = p.n_unusable
        timing = {"seconds": seconds, "seconds_per_instance": seconds / n}
        # *-lo methods: the LO budget actually spent (rlsac.estimation.lo.CountingEstimate)
        if hasattr(estimate, "summary"):
            for k, v in estimate.summary(n, seconds).items():
                (timing if k in TIMING_KEYS else summary)[k] = v
        ids = {k: data[k] for k in ("scene", "pair") if k in data and len(data[k]) == n}  # fundamental pairs
        rows = validity.kept_rows(p.attrs.get(validity.REPORT), n)  # the instances' rows in the file
        frame = pd.DataFrame({"instance": rows, **ids, **errors, "n_inliers": counts})
        csv_path, json_path = out_dir / "errors.csv", out_dir / "summary.json"
        with atomic_path(csv_path) as tmp:
            frame.to_csv(tmp, index=False, float_format="%.6g")
        # the full resolved configuration of this result (method, budget, sampling, checkpoint, task options)
        write_json(out_dir / "config.json", {k: _plain(v) for k, v in params.items()})
        write_json(json_path, summary)
        # timings vary from run to run: an untracked sidecar (git- and dvc-ignored) and MLflow, never summary.json,
        # so that a re-run of a stage gives the same bytes
        write_json(out_dir / TIMING_FILE, timing)
        summary.update(timing, out_dir=str(out_dir))
        mlrun.metrics({**{k: v for k, v in summary.items() if isinstance(v, (int, float)) and not isinstance(v, bool)
                          and k not in ("iterations", "seed", "steps_per_episode")}, "n_unusable": p.n_unusable})
        mlrun.artifact(csv_path)
        mlrun.artifact(json_path)
        summary["run_id"] = mlrun.run_id
    return summary


def recorded_options(o: EvalOptions) -> dict[str, Any]:
    """The checked options ``o`` as an evaluation records them (config.json, MLflow params): all but its run tags and
    the options its method does not read (``NOT_RECORDED``)."""
    skip = {"tags", *NOT_RECORDED.get(o.method.removesuffix("-lo"), ())}
    return {k: v for k, v in o.as_dict().items() if k not in skip}


def format_summary(summary: dict[str, Any]) -> str:
    """One line: method, data and the task's metrics."""
    skip = {"task", "method", "iterations", "data", "checkpoint", "seed", "device", "n_instances", "seconds",
            "seconds_per_instance", "out_dir", "run_id", "steps_per_episode", "n", "lo"}
    metrics = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                        for k, v in summary.items() if k not in skip)
    return (f"{summary['method']} on {summary['data']} ({summary['n_instances']} instances, "
            f"{summary['iterations']} it): {metrics}; {summary['seconds_per_instance'] * 1e3:.2f} ms/instance "
            f"-> {summary['out_dir']}")


def _task_options(task) -> dict[str, Any]:
    """The task's options (its dataclass fields), as resolved for this run."""
    import dataclasses

    return dataclasses.asdict(task) if dataclasses.is_dataclass(task) else {}


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    return v
