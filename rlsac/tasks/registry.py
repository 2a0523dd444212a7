"""The task registry: the ``Task`` protocol every estimation problem implements, ``register_task`` and the
look-ups (``task_class``, ``task_for``, ...), and reading a task's data file into a batch (``read_batch``).

Shapes: B batch rows, N points, m minimal size, d coordinate channels the solver uses, S solutions
per minimal set (1 for a line or the 8-point F, up to 10 for the five-point E) and H the hypothesis
shape (3 for a line, (3, 3) for a fundamental or essential matrix).
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

import numpy as np
import torch

from rlsac.errors import RlsacError


class Task(Protocol):
    # registry data, class attributes of the task class
    name: ClassVar[str]
    experiment: ClassVar[str]  # MLflow experiment of its runs
    default_iterations: ClassVar[int]  # hypotheses per instance when --iterations is not given
    residual_dof: ClassVar[int]  # degrees of freedom of a residual (MAGSAC++'s marginalisation, rlsac.estimation.lo)
    true_inlier_data: ClassVar[bool]  # its data files carry the true inlier mask (method oracle)

    sample_size: int  # m, points in a minimal set
    coord_dim: int  # d, channels of ``coords`` the solver needs
    threshold: float  # inlier threshold on ``residuals``
    feature_dim: int  # c, channels of ``features(batch)``, the network's data features
    solutions: int  # S, hypotheses per minimal set (``solve`` returns (B, S, *H) when S > 1)
    # (optional, default True) the output is refined on its inliers (rlsac.estimation.baselines.finalize); LO's refits
    # (rlsac.estimation.lo) are kept only when they score better, whatever this says
    refit_output: bool

    @staticmethod
    def read(path) -> tuple[dict[str, np.ndarray], dict]:
        """Read and validate a data file -> (arrays, attrs); RlsacError on a bad file."""

    @staticmethod
    def to_batch(arrays: dict, idx=slice(None), device="cpu") -> dict:
        """Rows ``idx`` of ``read``'s arrays -> the batch dict (coords (B, N, d), mask (B, N), ...)."""

    def features(self, batch: dict) -> torch.Tensor:
        """Normalised per-point data features for the policy network. -> (B, N, c)"""

    def solve(self, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Minimal solver. pts (B, m, d) -> hypotheses (B, *H), valid (B,) bool (False = degenerate);
        with S > 1 solutions: (B, S, *H), (B, S). Scored by ``rlsac.estimation.lo.score_sets`` only."""

    def residuals(self, hyps: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """hyps (B, *H), coords (B, N, d) -> residuals (B, N), compared against ``threshold``; also
        hyps (B, S, *H), S hypotheses per instance -> (B, S, N) (``rlsac.estimation.lo.score_sets`` scores so)."""

    def true_inliers(self, batch: dict) -> torch.Tensor:
        """Ground-truth inlier labels (B, N) bool, for the supervised warm start (not in the paper)."""

    def refine(self, coords: torch.Tensor, inliers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Non-minimal fit on inliers. coords (B, N, d), inliers (B, N) bool -> hyps (B, *H), valid (B,)."""

    def errors(self, hyps: np.ndarray, valid: np.ndarray, inliers: np.ndarray, batch: dict) -> dict[str, np.ndarray]:
        """Per-row errors against the ground truth in ``batch`` (numpy), e.g. {'err': (B,)} in degrees."""

    def summarize(self, errors: dict[str, np.ndarray]) -> dict[str, float]:
        """Dataset-level metrics (mAA, medians) from the concatenated per-row errors."""

    # Optional capabilities, looked up by the methods that need them (rlsac.evaluation.methods):
    #   match_quality(batch) -> (B, N), lower = better match: methods guided and prosac
    #   opencv_fit(pts (n, d) float64 numpy, flag, threshold, confidence, iterations) -> (hyp, inliers (n,)) or
    #       None, with opencv_threshold and hypothesis_shape (H): OpenCV's robust estimator of the task
    #       (opencv_ransac, usac, magsac, ...)


TASKS: dict[str, type] = {}


def register_task(cls: type) -> type:
    """Class decorator: add a task class to ``TASKS`` under its ``name`` (unique)."""
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"{cls.__name__} needs a class attribute 'name'")
    if name in TASKS and TASKS[name] is not cls:
        raise ValueError(f"task '{name}' is registered twice ({TASKS[name].__name__}, {cls.__name__})")
    for attr in ("experiment", "default_iterations", "residual_dof", "read", "to_batch"):
        if not hasattr(cls, attr):
            raise TypeError(f"task class {cls.__name__} lacks '{attr}'")
    TASKS[name] = cls
    return cls


def task_class(name: str) -> type:
    """The registered class of task ``name``; RlsacError for an unknown name."""
    if name not in TASKS:
        raise RlsacError(f"unknown task '{name}' (known: {', '.join(TASKS)})")
    return TASKS[name]


def get_task(name: str, **options) -> Task:
    """Task ``name`` built with ``options`` (its dataclass fields: threshold, residual, ...)."""
    return task_class(name)(**options)


def task_from(name: str, options: dict[str, Any] | None = None) -> Task:
    """Build task ``name`` with ``options`` (e.g. the ``task`` section stored in a checkpoint)."""
    options = dict(options or {})
    stored = options.pop("name", None)
    if stored is not None and stored != name:
        raise RlsacError(f"checkpoint was trained for task '{stored}', not '{name}'")
    try:
        return get_task(name, **options)
    except TypeError as e:
        raise RlsacError(f"bad options for task '{name}': {e}") from None


def task_for(o: Any, options: dict[str, Any] | None = None) -> Task:
    """The task of the checked evaluate options ``o`` (rlsac.evaluation.evaluate.EvalOptions: its task, threshold_px and
    refit_output are read; with ``options``, e.g. a checkpoint's), its inlier
    threshold set from ``o.threshold_px`` and its final refit from ``o.refit_output`` when given."""
    import dataclasses

    task = task_from(o.task, options)
    if o.threshold_px is not None:
        task = dataclasses.replace(task, threshold=task.px_thresholds(o.threshold_px)[0])
    if o.refit_output is not None:
        if not hasattr(task, "refit_output"):
            raise RlsacError(f"task '{task.name}' has no refit_output option")
        task = dataclasses.replace(task, refit_output=bool(o.refit_output))
    return task


def opencv_threshold(o: Any, task: Task) -> float:
    """OpenCV's threshold for ``o``: the task's default, or ``o.threshold_px`` in OpenCV's unit."""
    return task.opencv_threshold if o.threshold_px is None else task.px_thresholds(o.threshold_px)[1]


def prefiltered(task: Task, batch: dict, prefilter: float | torch.Tensor | None, keep_short: bool = False) -> dict:
    """``batch`` with mask (B, N) cleared where the match quality (the SNN ratio) is above ``prefilter``: the
    tutorial's pre-filter, applied before any method sees the pair (None: the batch unchanged). ``prefilter``: one
    ratio, or a (B,) tensor of one per instance (training draws one per episode, rlsac.rl.episodes). ``keep_short``: an
    instance the filter would leave with fewer points than a minimal sample keeps its mask (training's episodes
    need a sample; the evaluation scores such a pair as it comes)."""
    if prefilter is None:
        return batch
    quality = task.match_quality(batch)
    ratio = prefilter[:, None].to(quality.dtype) if torch.is_tensor(prefilter) else float(prefilter)
    keep = batch["mask"] & (quality <= ratio)
    if keep_short:
        keep = torch.where(keep.sum(-1, keepdim=True) >= task.sample_size, keep, batch["mask"])
    return {**batch, "mask": keep}


def task_names() -> tuple[str, ...]:
    return tuple(TASKS)


def load(task: str, path, device: str | torch.device = "cpu", idx=slice(None)) -> dict:
    """Read a data file of task ``task`` (its registered reader) into the batch dict the task, env and
    baselines use."""
    return read_batch(task, path, device, idx)[0]


def read_batch(task: str, path, device: str | torch.device = "cpu", idx=slice(None)) -> tuple[dict, dict]:
    """``load``, with the file's attributes (and the reader's report of the instances it left out as unusable,
    attrs["unusable"]: rlsac.data.validity) -> (batch, attrs)."""
    cls = task_class(task)
    arrays, attrs = cls.read(path)
    return cls.to_batch(arrays, idx, device), attrs


def as_numpy(v):
    """torch tensor (any device) or array -> numpy (what ``Task.errors`` reads)."""
    return v.detach().cpu().numpy() if torch.is_tensor(v) else np.asarray(v) if isinstance(v, np.ndarray) else v
