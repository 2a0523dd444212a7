"""Hypothesis scoring and local optimisation (LO), shared by every sampler of ours.

RANSAC (``rlsac.estimation.baselines.ransac``), the uniform control and RLSAC (``rlsac.rl.env``) all keep "the best
hypothesis so far" per instance through ``update_best``: it scores a group of candidate hypotheses per
instance, and when the group's best beats the best so far (``LOConf.trigger``: the best LO-improved
score, or the best unoptimised one) it runs ``local_optimization`` on it (if enabled) and keeps the
result if it beats the best. ``finish`` turns the best hypothesis into the output.

Scores (higher is better; ``LOConf.score``):

* ``count``: the inlier count (residual <= threshold), the paper's and plain RANSAC's score;
* ``msac``: MSAC's truncated quadratic, sum over points of 1 - min(r^2 / t^2, 1) (Torr & Zisserman);
* ``magsac``: MAGSAC++'s marginalised quality (Barath et al., CVPR 2020), sum of 1 - rho(r) / rho(k sigma_max)
  with the loss rho marginalised over a uniform noise scale sigma in [0, sigma_max] (closed form below).

The LO step (LO-RANSAC, Chum et al. 2003/2012, with MAGSAC++'s iteratively reweighted least squares when
``score="magsac"``): ``inner_samples`` non-minimal fits on random subsets of the hypothesis' inliers
(inner RANSAC), then ``iterations`` reweighted refits, each weighting the points by the previous fit's
residuals (inlier mask for count/MSAC, MAGSAC++ weights for magsac). Every candidate is scored and kept
only if its score is at least the best one's, so the step never returns a worse-scoring hypothesis. Its
budget is bounded (inner_samples + iterations non-minimal fits per call) and counted (``Best.lo_fits``).

Residual units: a task's ``residuals`` are compared with its ``threshold``; the fundamental task's
default ``sampson_sq`` residual is already a squared distance (px^2), every other one a distance. The
scores work on squared distances (``_squared_residuals``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from rlsac.errors import RlsacError
from rlsac.tasks import Task

SCORES = ("count", "msac", "magsac")
# sqrt of the 0.99 quantile of chi^2 with `dof` degrees of freedom: MAGSAC++'s k (OpenCV uses 3.64 for dof 4)
CHI_QUANTILE_99 = {2: 3.0349, 3: 3.3682, 4: 3.6437}


@dataclass
class LOConf:
    enabled: bool = False  # off: the samplers behave exactly as without this module
    score: str = "count"  # how the best hypothesis is chosen: count | msac | magsac
    inner_samples: int = 0  # inner RANSAC: non-minimal fits on random subsets of the inliers per LO call
    sample_factor: int = 7  # inner subset size = min(sample_factor * m, inliers) (LO-RANSAC's 7m ... 14m)
    iterations: int = 4  # reweighted least-squares refits per LO call, after the inner RANSAC
    threshold_scale: float = 1.0  # refit weights: inliers of scale * threshold, shrinking to 1 * threshold
    # refit weights: "inliers" (least squares on the inliers, LO-RANSAC), "magsac" (MAGSAC++ weights, IRLS)
    # or "auto" (magsac weights for the magsac score, inliers otherwise)
    weighting: str = "auto"
    sigma_scale: float = 1.0  # magsac: sigma_max = sigma_scale * threshold (as a distance), as OpenCV's MAGSAC++
    dof: int | None = None  # magsac: residual degrees of freedom (None: 2 for lines, 4 for F as OpenCV)
    final: bool = True  # one more LO call on the output, instead of the unconditional least-squares refit
    # when LO runs: "best" = a candidate beats the best-so-far score, LO-improved (LO-RANSAC, USAC); "minimal" =
    # it beats the best *unoptimised* candidate so far (more calls: a sampler's later, better minimal sets are
    # optimised too instead of having to beat a polished score); the result is kept only if it beats the best
    trigger: str = "best"

    def __post_init__(self) -> None:
        if self.score not in SCORES:
            raise RlsacError(f"unknown LO score {self.score!r} (known: {', '.join(SCORES)})")
        if self.trigger not in ("best", "minimal"):
            raise RlsacError(f"unknown LO trigger {self.trigger!r} (known: best, minimal)")
        if self.weighting not in ("auto", "inliers", "magsac"):
            raise RlsacError(f"unknown LO weighting {self.weighting!r} (known: auto, inliers, magsac)")
        if self.inner_samples < 0 or self.iterations < 0 or self.sample_factor < 1:
            raise RlsacError("LO inner_samples and iterations must be >= 0 and sample_factor >= 1")
        if self.threshold_scale < 1.0 or self.sigma_scale <= 0.0:
            raise RlsacError("LO threshold_scale must be >= 1 and sigma_scale > 0")
        if self.dof is not None and self.dof not in CHI_QUANTILE_99:
            raise RlsacError(f"LO dof must be one of {sorted(CHI_QUANTILE_99)} (closed-form MAGSAC++ loss)")

    @property
    def fits_per_call(self) -> int:
        return self.inner_samples + self.iterations


def active(conf: LOConf | None) -> bool:
    return conf is not None and conf.enabled


# ------------------------------------------------------------------------------------------ scoring


def _squared_residuals(task: Task, res: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Residuals and threshold as squared distances: (res^2, t^2), or as they are for ``sampson_sq``."""
    if getattr(task, "residual", None) == "sampson_sq":
        return res, float(task.threshold)
    return res.square(), float(task.threshold) ** 2


def _magsac_constants(task: Task, conf: LOConf, t2: float) -> tuple[float, float, float, float]:
    """-> (a0, a1, 2 sigma_max^2, x_k) for the MAGSAC++ loss in x = r^2 / (2 sigma_max^2)."""
    dof = conf.dof if conf.dof is not None else type(task).residual_dof
    k = CHI_QUANTILE_99[dof]
    two_sigma2 = 2.0 * conf.sigma_scale ** 2 * t2
    return (dof - 1) / 2.0, (dof + 1) / 2.0, two_sigma2, k * k / 2.0


def _gammainc(a: float, x: torch.Tensor) -> torch.Tensor:
    """Regularised lower incomplete gamma P(a, x) for a half-integer a > 0 (all MAGSAC++ needs for
    dof 2-4), in closed form: P(1/2, x) = erf(sqrt x), P(1, x) = 1 - e^-x, P(b + 1, x) = P(b, x) -
    x^b e^-x / G(b + 1). torch.special.gammainc gives the same values but is ~10x slower on CPU."""
    if a <= 0 or abs(2 * a - round(2 * a)) > 1e-9:
        raise RlsacError(f"_gammainc: a must be a positive half-integer, got {a}")
    b = 0.5 if abs(a - round(a)) > 1e-9 else 1.0
    p = torch.erf(x.sqrt()) if b == 0.5 else -torch.expm1(-x)
    while b < a - 1e-9:
        p = p - x.pow(b) * torch.exp(-x) / math.gamma(b + 1)
        b += 1.0
    return p


def _magsac_loss(x: torch.Tensor, a0: float, a1: float, xk: float) -> torch.Tensor:
    """MAGSAC++ loss up to a positive constant, in x = r^2 / (2 sigma_max^2), constant beyond x_k.

    rho(x) = G(a1) P(a1, x) + x G(a0) (Q(a0, x) - Q(a0, x_k)), with P, Q = 1 - P the regularised lower /
    upper incomplete gamma functions and a0 = (dof - 1) / 2, a1 = a0 + 1: the marginalisation over sigma
    in [0, sigma_max] of the chi-distributed residual's negative log-likelihood (MAGSAC++ Eq. 6, divided by
    sigma_max^2). d rho / dx = G(a0) (Q(a0, x) - Q(a0, x_k)): the IRLS weight ``_magsac_weight``.
    """
    x = x.clamp(0.0, xk)
    qk = 1.0 - _gammainc(a0, torch.full((1,), xk, dtype=x.dtype, device=x.device))
    return math.gamma(a1) * _gammainc(a1, x) + x * math.gamma(a0) * ((1.0 - _gammainc(a0, x)) - qk)


def _magsac_weight(x: torch.Tensor, a0: float, xk: float) -> torch.Tensor:
    """MAGSAC++ IRLS weight in [0, 1] (1 at r = 0, 0 from r = k sigma_max on)."""
    qk = 1.0 - _gammainc(a0, torch.full((1,), xk, dtype=x.dtype, device=x.device))
    w = ((1.0 - _gammainc(a0, x.clamp(0.0, xk))) - qk) / (1.0 - qk)
    return w.clamp_min(0.0)


def score(task: Task, conf: LOConf, res: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Score of hypotheses from their residuals; higher is better.

    res (..., N) residuals in the task's unit (non-finite = outlier), mask (..., N) valid points ->
    (...) float64: the inlier count (``count``), the MSAC or the MAGSAC++ quality, each in [0, N].
    """
    if res.shape[-1] != mask.shape[-1]:
        raise RlsacError(f"score: residuals {tuple(res.shape)} and mask {tuple(mask.shape)} disagree")
    finite = torch.isfinite(res) & mask
    if conf.score == "count":
        return ((res <= task.threshold) & finite).sum(-1).double()
    r2, t2 = _squared_residuals(task, res.double())
    r2 = torch.where(finite, r2, torch.full_like(r2, math.inf))
    if conf.score == "msac":
        return (1.0 - (r2 / t2).clamp(max=1.0)).masked_fill(~finite, 0.0).sum(-1)
    a0, a1, two_sigma2, xk = _magsac_constants(task, conf, t2)
    x = (r2 / two_sigma2).clamp(max=xk)
    rho_max = _magsac_loss(torch.full((1,), xk, dtype=torch.float64, device=res.device), a0, a1, xk)
    return (1.0 - _magsac_loss(x, a0, a1, xk) / rho_max).masked_fill(~finite, 0.0).sum(-1)


def weights(task: Task, conf: LOConf, res: torch.Tensor, mask: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """Weights of a non-minimal refit from the current fit's residuals. res, mask (B, N) -> (B, N).

    count / msac: the inliers at ``scale`` * threshold (bool: the refit is plain least squares on them,
    which is also the IRLS step of the truncated quadratic); magsac: MAGSAC++'s marginalised weights
    (float64; ``scale`` widens sigma_max).
    """
    finite = torch.isfinite(res) & mask
    r2, t2 = _squared_residuals(task, res.double())
    r2 = torch.where(finite, r2, torch.full_like(r2, math.inf))
    if conf.weighting == "inliers" or (conf.weighting == "auto" and conf.score != "magsac"):
        return (r2 <= t2 * scale * scale) & finite
    a0, _, two_sigma2, xk = _magsac_constants(task, conf, t2)
    w = _magsac_weight(r2.clamp(max=1e300) / (two_sigma2 * scale * scale), a0, xk)
    return w.masked_fill(~finite, 0.0)


# ------------------------------------------------------------------------------ local optimisation


def _check(coords: torch.Tensor, mask: torch.Tensor, hyp: torch.Tensor, rows: int) -> None:
    B = coords.shape[0]
    if coords.dim() != 3 or mask.shape != coords.shape[:2] or hyp.shape[0] != B or rows != B:
        raise RlsacError(f"LO: coords (B, N, d) {tuple(coords.shape)}, mask (B, N) {tuple(mask.shape)}, "
                         f"hyp (B, *H) {tuple(hyp.shape)} and scores (B,) ({rows}) disagree")


def _rows(x: torch.Tensor, keep: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
    """Per-row select: new where keep (B,) else x; x, new (B, ...)."""
    return torch.where(keep.view(-1, *[1] * (x.dim() - 1)), new, x)


def _scored_fit(task: Task, conf: LOConf, coords, mask, w) -> tuple[torch.Tensor, torch.Tensor]:
    """Non-minimal fit with weights w (B, N) -> hyp (B, *H), score (B,) (-inf where the fit fails)."""
    h, ok = task.refine(coords, w)
    s = score(task, conf, task.residuals(h, coords), mask)
    return h, s.masked_fill(~ok, -math.inf)


@torch.no_grad()
def local_optimization(task: Task, conf: LOConf, coords: torch.Tensor, mask: torch.Tensor, hyp: torch.Tensor,
                       hyp_score: torch.Tensor, generator: torch.Generator | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The LO step on a batch of hypotheses: bounded non-minimal refits, improvements only.

    coords (B, N, d), mask (B, N) bool, hyp (B, *H), hyp_score (B,) its ``score`` ->
    hyp (B, *H), score (B,) float64 with score >= hyp_score row by row, fits: non-minimal fits per row
    (conf.inner_samples + conf.iterations). ``generator`` draws the inner RANSAC subsets.
    """
    _check(coords, mask, hyp, hyp_score.shape[0])
    B, N, _ = coords.shape
    best_h, best_s = hyp, hyp_score.double()
    if conf.inner_samples > 0:
        # inner RANSAC: K random subsets of min(sample_factor m, n) of the current inliers, one fit each
        K = conf.inner_samples
        inl = weights(task, conf, task.residuals(hyp, coords), mask, conf.threshold_scale) > 0
        size = inl.sum(-1).clamp(max=conf.sample_factor * task.sample_size).clamp_min(1)  # (B,)
        keys = torch.rand((B, K, N), generator=generator, device=coords.device, dtype=torch.float64)
        keys = keys.masked_fill(~inl[:, None], -1.0)
        kth = keys.sort(-1, descending=True).values.gather(-1, (size - 1).view(B, 1, 1).expand(B, K, 1))
        sub = (keys >= kth) & inl[:, None]  # the `size` inliers with the largest keys
        h, s = _scored_fit(task, conf, coords.repeat_interleave(K, 0), mask.repeat_interleave(K, 0),
                           sub.flatten(0, 1))
        s, j = s.view(B, K).max(1)
        h = h.view(B, K, *h.shape[1:])[torch.arange(B, device=coords.device), j]
        take = s >= best_s
        best_h, best_s = _rows(best_h, take, h), torch.where(take, s, best_s)
    cur = best_h
    n = conf.iterations
    for i in range(n):
        # LO+'s threshold schedule: a wider band first (recovers inliers a poor fit misses), down to 1x
        scale = conf.threshold_scale + (1.0 - conf.threshold_scale) * (i / (n - 1) if n > 1 else 1.0)
        h, s = _scored_fit(task, conf, coords, mask, weights(task, conf, task.residuals(cur, coords), mask, scale))
        # ties go to the non-minimal fit: same support, averaged over more points than a minimal sample
        take = s >= best_s
        best_h, best_s = _rows(best_h, take, h), torch.where(take, s, best_s)
        cur = _rows(cur, torch.isfinite(s), h)  # follow the IRLS trajectory; the best is kept aside
    return best_h, best_s, conf.fits_per_call


# ------------------------------------------------------------------------ best-so-far bookkeeping


@dataclass
class Best:
    """Best hypothesis so far per instance, and the LO budget spent on it (counted per instance)."""

    hyp: torch.Tensor | None  # (B, *H), None before the first update
    count: torch.Tensor  # (B,) long: its inlier count (-1 = none yet)
    score: torch.Tensor  # (B,) float64: its score under LOConf.score (-inf = none yet); count when LO is off
    lo_calls: torch.Tensor  # (B,) long: LO steps run
    lo_fits: torch.Tensor  # (B,) long: non-minimal fits spent by them
    lo_seconds: float = 0.0  # wall time inside the LO steps (benchmarks/lo.py)
    raw: torch.Tensor | None = None  # (B,) float64: best unoptimised candidate score (LOConf.trigger="minimal")

    @classmethod
    def empty(cls, B: int, device) -> Best:
        return cls(None, torch.full((B,), -1, dtype=torch.long, device=device),
                   torch.full((B,), -math.inf, dtype=torch.float64, device=device),
                   torch.zeros(B, dtype=torch.long, device=device), torch.zeros(B, dtype=torch.long, device=device),
                   raw=torch.full((B,), -math.inf, dtype=torch.float64, device=device))


@torch.no_grad()
def update_best(task: Task, conf: LOConf | None, coords: torch.Tensor, mask: torch.Tensor, best: Best,
                hyps: torch.Tensor, count: torch.Tensor, res: torch.Tensor | None = None,
                generator: torch.Generator | None = None) -> Best:
    """Fold a group of k candidates per instance into the best so far (the one RANSAC scoring loop).

    coords (B, N, d), mask (B, N): the instances; hyps (B, k, *H) candidates; count (B, k) their inlier
    counts, < 0 for candidates that may not compete (degenerate, inactive); res (B, k, N) their residuals
    (needed when LO is on). LO off: the candidate with most inliers replaces the best if it has more (ties
    keep the earlier one, as a sequential RANSAC would). LO on: the group's best by ``conf.score`` is
    locally optimised when it beats the best score (trigger "best") or the best unoptimised score so far
    (trigger "minimal"), and stored if the result beats the best. -> the updated ``best`` (new tensors).
    """
    B, k = count.shape
    if hyps.shape[:2] != (B, k) or coords.shape[0] != B:
        raise RlsacError(f"update_best: hyps {tuple(hyps.shape)}, count {tuple(count.shape)}, "
                         f"coords {tuple(coords.shape)} disagree")
    rows = torch.arange(B, device=count.device)
    if not active(conf):
        c, j = count.max(dim=1)
        h = hyps[rows, j]
        better = c > best.count
        hyp = h if best.hyp is None else _rows(best.hyp, better, h)
        return Best(hyp, torch.where(better, c, best.count), torch.where(better, c.double(), best.score),
                    best.lo_calls, best.lo_fits, best.lo_seconds, best.raw)
    if res is None or res.shape[:2] != (B, k):
        raise RlsacError("update_best with LO needs the candidates' residuals res (B, k, N)")
    s = score(task, conf, res, mask[:, None]).masked_fill(count < 0, -math.inf)
    smax, j = s.max(dim=1)
    h = hyps[rows, j]
    raw = best.raw if best.raw is not None else torch.full_like(best.score, -math.inf)
    trig = smax > (raw if conf.trigger == "minimal" else best.score)  # rows whose candidate gets LO
    hyp = h if best.hyp is None else best.hyp
    sc, calls, fits, seconds = best.score, best.lo_calls, best.lo_fits, best.lo_seconds
    idx = trig.nonzero().squeeze(1)
    if idx.numel():
        t0 = time.perf_counter()
        h2, s2, n = local_optimization(task, conf, coords[idx], mask[idx], h[idx], smax[idx], generator)
        take = s2 > sc[idx]  # always true for trigger "best" (LO never lowers a score that beat the best)
        keep = idx[take]
        hyp, sc = hyp.index_copy(0, keep, h2[take]), sc.index_copy(0, keep, s2[take])
        calls = calls.index_add(0, idx, torch.ones_like(idx))
        fits = fits.index_add(0, idx, torch.full_like(idx, n))
        seconds += time.perf_counter() - t0
    cnt = inlier_count(task, hyp, coords, mask)
    # rows that never had a competing candidate keep count -1 (no hypothesis yet)
    cnt = torch.where(sc > -math.inf, cnt, best.count)
    return Best(hyp, cnt, sc, calls, fits, seconds, torch.maximum(raw, smax))


@torch.no_grad()
def score_sets(task: Task, pts: torch.Tensor, coords: torch.Tensor, mask: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The one hypothesis-scoring step of every sampler (RANSAC, the RLSAC environment, the figures):
    solve each minimal set, score it by its inlier count, and of a multi-solution solver's candidates
    (``task.solutions`` > 1) keep the one with the most inliers.

    pts (B, S, m, d): S minimal sets of each of B instances; coords (B, N, d), mask (B, N) the instances ->
    hyps (B, S, *H), valid (B, S), residuals (B, S, N) (as ``task.residuals``, not masked), count (B, S)
    inliers among the valid points (callers mask invalid sets). The residuals of an instance's S x solutions
    hypotheses are one grouped ``task.residuals`` call on its points, not S copies of them.
    """
    if pts.dim() != 4 or coords.dim() != 3 or pts.shape[0] != coords.shape[0] or mask.shape != coords.shape[:2]:
        raise RlsacError(f"score_sets: pts (B, S, m, d), coords (B, N, d), mask (B, N) expected, got "
                         f"{tuple(pts.shape)}, {tuple(coords.shape)}, {tuple(mask.shape)}")
    B, S = pts.shape[:2]
    sol = getattr(task, "solutions", 1)
    hyps, valid = task.solve(pts.flatten(0, 1))  # (B S, *H), or (B S, sol, *H) for a multi-solution task
    H = hyps.shape[1 + (sol > 1):]
    res = task.residuals(hyps.reshape(B, S * sol, *H), coords).view(B, S, sol, -1)
    count = ((res <= task.threshold) & mask[:, None, None]).sum(-1)  # (B, S, sol)
    hyps, valid = hyps.reshape(B, S, sol, *H), valid.reshape(B, S, sol)
    if sol == 1:
        return hyps[:, :, 0], valid[:, :, 0], res[:, :, 0], count[:, :, 0]
    count = count.masked_fill(~valid, -1)
    pick = count.argmax(-1, keepdim=True)  # (B, S, 1)
    hyp = hyps.gather(2, pick.view(B, S, 1, *[1] * len(H)).expand(B, S, 1, *H)).squeeze(2)
    res = res.gather(2, pick[..., None].expand(B, S, 1, res.shape[-1])).squeeze(2)
    return hyp, valid.gather(2, pick).squeeze(2), res, count.gather(2, pick).squeeze(2).clamp_min(0)


def inlier_count(task: Task, hyp: torch.Tensor, coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """hyp (B, *H), coords (B, N, d), mask (B, N) -> (B,) long inliers at the task's threshold."""
    return ((task.residuals(hyp, coords) <= task.threshold) & mask).sum(-1)


@torch.no_grad()
def finish(task: Task, conf: LOConf, coords: torch.Tensor, mask: torch.Tensor, best: Best,
           generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    """The output with LO on: one more LO step on every valid best hypothesis (``conf.final``), which
    keeps a refit only where it scores at least as well, then its inliers.

    -> hyp (B, *H), valid (B,), inliers (B, N), best_count (B,), lo_calls / lo_fits (B,), lo_seconds.
    """
    hyp, sc = best.hyp, best.score
    valid = best.count >= task.sample_size
    calls, fits, seconds = best.lo_calls, best.lo_fits, best.lo_seconds
    idx = valid.nonzero().squeeze(1)
    if conf.final and idx.numel():
        t0 = time.perf_counter()
        h2, s2, n = local_optimization(task, conf, coords[idx], mask[idx], hyp[idx], sc[idx], generator)
        hyp, sc = hyp.index_copy(0, idx, h2), sc.index_copy(0, idx, s2)
        calls = calls.index_add(0, idx, torch.ones_like(idx))
        fits = fits.index_add(0, idx, torch.full_like(idx, n))
        seconds += time.perf_counter() - t0
    inl = (task.residuals(hyp, coords) <= task.threshold) & mask & valid[:, None]
    return {"hyp": hyp, "valid": valid, "inliers": inl, "best_count": inl.sum(-1), "score": sc,
            "lo_calls": calls, "lo_fits": fits, "lo_seconds": seconds}


# ------------------------------------------------------------------------------------- evaluation


def lo_conf(options: dict | None, where: str = "evaluate.lo") -> LOConf:
    """LOConf(options, enabled), typed and range-checked (params.yaml ``evaluate.<task>.lo``; ``where`` names it
    in errors)."""
    from rlsac.config import build

    return build(LOConf, {**(options or {}), "enabled": True}, where)


def conf_for_method(method: str, options: dict | None) -> LOConf | None:
    """The LO of an evaluate method: ``<base>-lo`` -> ``lo_conf(options)``, any other method -> None (no LO,
    whatever ``options`` say)."""
    return lo_conf(options) if method.endswith("-lo") else None


class CountingEstimate:
    """Wraps an ``estimate(batch, generator)`` whose outputs carry lo_calls / lo_fits / lo_seconds and
    sums them over an evaluation, for its summary (the LO budget is counted and reported)."""

    def __init__(self, estimate) -> None:
        self.estimate = estimate
        self.calls = self.fits = 0
        self.seconds = 0.0

    def __call__(self, batch: dict, generator: torch.Generator | None = None) -> dict:
        out = self.estimate(batch, generator)
        self.calls += int(out["lo_calls"].sum())
        self.fits += int(out["lo_fits"].sum())
        self.seconds += float(out["lo_seconds"])
        return out

    def summary(self, n: int, seconds: float) -> dict[str, float]:
        """Per instance: LO calls, non-minimal fits, seconds; and LO's share of the total time."""
        n = max(int(n), 1)
        return {"lo_calls_per_instance": self.calls / n, "lo_fits_per_instance": self.fits / n,
                "lo_seconds_per_instance": self.seconds / n,
                "lo_time_fraction": self.seconds / seconds if seconds > 0 else float("nan")}
