"""Shared timing helpers of the benchmarks: where the time of an RLSAC rollout goes, and OpenCV's budget.

``Split`` wraps (while active) the actor's forward paths, minimal-set selection, the environment's
``step`` (minimal solver, residuals / inlier counts, memory update), ``state`` (the per-step
concatenation of the reference path) and ``result`` (final refinement), and adds their time into
buckets; ``other`` is what is left of the total (setup, kNN graph, bookkeeping).

Clock: the process's CPU time (``CLOCK``). The benchmarks run torch (and OpenCV) on one thread, where
CPU time equals wall time on an idle machine; on the shared 2-core machine it leaves out the time the
process waits for a core, which otherwise swings ratios by 2x between runs. Wall time is printed too.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from contextlib import contextmanager

import numpy as np

import rlsac.rl.rollout as rollout
from rlsac.rl.env import SampleConsensusEnv

BUCKETS = ("model", "selection", "solver+scoring", "state", "refine", "other")


def add_sampler_args(ap, task: str) -> None:
    """``--policy-every``, ``--sets-per-step`` and ``--confidence`` of "RLSAC after" (see ``sampler_args``)."""
    ap.add_argument("--policy-every", type=int, default=1,
                    help="RLSAC after: recompute the policy every N steps (not in the paper; 1 = the paper)")
    ap.add_argument("--sets-per-step", type=int, default=None,
                    help=f"RLSAC after: minimal sets per environment step [default: params.yaml evaluate.{task}]")
    ap.add_argument("--confidence", type=float, default=None,
                    help="RLSAC after: stop at RANSAC's bound for this confidence [default: params.yaml]")


def sampler_args(args, task: str) -> None:
    """Fill ``args.sets_per_step`` / ``args.confidence`` left unset from params.yaml evaluate.<task>, as
    ``rlsac evaluate`` does (1 and 0, the paper, without a params file)."""
    from rlsac.config import read_params, section
    from rlsac.evaluation.evaluate import sampler_options

    params = read_params("params.yaml")
    given = {"sets_per_step": 1, "confidence": 0.0, **sampler_options(section(params, "evaluate", task))}
    args.sets_per_step = int(given["sets_per_step"]) if args.sets_per_step is None else args.sets_per_step
    args.confidence = float(given["confidence"]) if args.confidence is None else args.confidence
CLOCK = time.process_time


class Split:
    def __init__(self, actor):
        self.actor = actor
        self.seconds: dict[str, float] = defaultdict(float)
        self.total = 0.0
        self._undo: list = []

    def _wrap(self, fn, bucket):
        def timed(*args, **kwargs):
            t0 = CLOCK()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[bucket] += CLOCK() - t0
        return timed

    def __enter__(self) -> Split:
        for name in ("forward_memory", "precompute", "reference_forward"):
            if hasattr(self.actor, name):
                setattr(self.actor, name, self._wrap(getattr(self.actor, name), "model"))
                self._undo.append(lambda n=name: delattr(self.actor, n))
        env = SampleConsensusEnv
        for owner, name, bucket in ((rollout, "select_lazily", "selection"), (env, "select", "selection"),
                                    (env, "select_many", "selection"),
                                    (env, "step", "solver+scoring"), (env, "state", "state"),
                                    (env, "result", "refine")):
            orig = getattr(owner, name)
            setattr(owner, name, self._wrap(orig, bucket))
            self._undo.append(lambda o=owner, n=name, f=orig: setattr(o, n, f))
        return self

    def __exit__(self, *exc) -> None:
        for undo in reversed(self._undo):
            undo()
        self._undo.clear()

    @contextmanager
    def timed(self):
        """Time one call; the sum of these is the total the buckets are split from."""
        t0 = CLOCK()
        yield
        self.total += CLOCK() - t0

    def parts(self) -> dict[str, float]:
        out = {b: self.seconds.get(b, 0.0) for b in BUCKETS[:-1]}
        out["other"] = max(self.total - sum(out.values()), 0.0)
        return out


def format_split(rows: dict[str, Split], per: int, unit: str) -> str:
    """Table: one line per named Split, ms per ``unit`` and share of each bucket."""
    head = f"{'':22s} {'total':>9s} " + " ".join(f"{b:>16s}" for b in BUCKETS)
    lines = [f"CPU time per {unit}, ms (share)", head]
    for name, s in rows.items():
        p = s.parts()
        cells = " ".join(f"{1e3 * v / per:9.2f} ({100 * v / max(s.total, 1e-12):3.0f}%)" for v in p.values())
        lines.append(f"{name:22s} {1e3 * s.total / per:9.2f} {cells}")
    return "\n".join(lines)


def opencv_hypotheses(inliers: np.ndarray, mask: np.ndarray, iterations: int, confidence: float = 0.999,
                      m: int = 8) -> np.ndarray:
    """Hypotheses OpenCV's adaptive termination allows once it holds its final model: min(maxIters,
    ceil(log(1 - confidence) / log(1 - w^m))) with w its final inlier ratio. OpenCV does not report
    its iteration count; the loop stops at the first iteration past this bound for its best-so-far
    model, so this is an estimate (a lower bound when the best model came late)."""
    w = inliers.sum(-1) / np.maximum(mask.sum(-1), 1)
    out = np.full(w.shape, float(iterations))
    ok = (w > 0) & (w < 1)
    out[ok] = np.minimum(iterations, np.ceil(math.log(1 - confidence) / np.log1p(-w[ok] ** m)))
    out[w >= 1] = 1
    return out


class Clocks:
    """Accumulates CPU and wall seconds of timed blocks: ``with clocks: ...``."""

    def __init__(self):
        self.cpu = self.wall = 0.0

    def __enter__(self):
        self._c, self._w = CLOCK(), time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.cpu += CLOCK() - self._c
        self.wall += time.perf_counter() - self._w
        return False
