"""The evaluation methods, each registered once with how to build its estimator (no heavy imports at
module level: the CLI reads the names for --help; the builders import what they need).

A method's builder takes the checked evaluate options ``o`` (rlsac.evaluation.evaluate.EvalOptions, read by attribute),
the device and an optional LO conf and returns (task, estimate(batch, generator) -> {hyp, valid, inliers}, extra
run params). ``needs`` names the task capability it requires (rlsac.tasks.Task: an optional method or a true class
attribute), so evaluate rejects an unsupported (task, method) pair before any work, whatever the task.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable


@dataclass(frozen=True)
class Method:
    name: str
    build: Callable[[Any, str, Any], tuple]  # (rlsac.evaluation.evaluate.EvalOptions, device, LO conf)
    needs: str | None = None  # task capability: "match_quality", "opencv_fit", "true_inlier_data"
    checkpoint: bool = False  # needs --checkpoint
    lo: bool = False  # the *-lo variant of a base method (rlsac.estimation.lo), not in the paper
    label: str = ""  # its name in tables and figures

    def unsupported(self, task_cls: type, tasks: dict[str, type]) -> str | None:
        """Why this method cannot run on ``task_cls`` (None when it can); ``tasks``: the registry."""
        if self.needs and not getattr(task_cls, self.needs, False):
            have = [n for n, c in tasks.items() if getattr(c, self.needs, False)]
            return (f"method '{self.name}' needs {CAPABILITIES[self.needs]}, which task '{task_cls.name}' has not "
                    f"(tasks with it: {', '.join(have) or 'none'})")
        return None


CAPABILITIES = {"match_quality": "per-point match quality (the SNN ratio)", "opencv_fit": "an OpenCV estimator",
                "degensac_fit": "a DEGENSAC estimator (pydegensac: fundamental matrices)",
                "poselib_fit": "a PoseLib estimator (fundamental matrix, relative pose)",
                "true_inlier_data": "the true inlier mask in its data (synthetic data)"}
METHODS: dict[str, Method] = {}


def register_method(name: str, label: str, needs: str | None = None, checkpoint: bool = False, lo: bool = False):
    """Decorator: register ``build`` as method ``name`` (unique), shown as ``label`` in tables and figures."""
    def deco(build):
        if name in METHODS:
            raise ValueError(f"method '{name}' is registered twice")
        METHODS[name] = Method(name, build, needs, checkpoint, lo, label)
        return build
    return deco


# ------------------------------------------------------------------------------ our samplers
@register_method("ransac", "RANSAC (our batched torch)")
def _ransac(o, device, lo=None):
    """Our batched RANSAC (uniform sets, inlier count, refinement), any task."""
    from rlsac.estimation.baselines import ransac
    from rlsac.tasks import task_for

    task = task_for(o)
    return task, lambda batch, g: ransac(task, batch, o.iterations, g, lo=lo), {}


@register_method("oracle", "Oracle (refit on the true inliers)", needs="true_inlier_data")
def _oracle(o, device, lo=None):
    """The refinement on the true inliers: the headroom of any sampler (synthetic data only)."""
    from rlsac.estimation.baselines import oracle
    from rlsac.tasks import task_for

    task = task_for(o)
    return task, lambda batch, g: oracle(task, batch), {}


def _environment(o, lo, guide=None):
    """The RLSAC environment without a policy: uniform sets, or sets drawn ~ exp(guide(task, batch))."""
    from rlsac.rl.checkpoint import env_conf
    from rlsac.rl.rollout import rlsac_estimate, with_lo
    from rlsac.tasks import task_for

    task = task_for(o)
    env = with_lo(env_conf({}, o.steps_per_episode), lo)

    def estimate(batch, g):
        return rlsac_estimate(task, batch, None, o.iterations, env, generator=g,
                              guide=None if guide is None else guide(task, batch),
                              sets_per_step=o.sets_per_step, confidence=o.confidence)
    return task, estimate, {"steps_per_episode": env.steps_per_episode}


@register_method("uniform", "Uniform (RLSAC env., uniform sets)")
def _uniform(o, device, lo=None):
    """The RLSAC environment with uniform minimal sets: RLSAC - uniform is the learned sampler alone."""
    return _environment(o, lo)


@register_method("guided", "Guided (RLSAC env., sets drawn by SNN; not in the paper)", needs="match_quality")
def _guided(o, device, lo=None):
    """The same environment, sets drawn ~ exp(-quality / guide_temperature): a hand-made guided sampler
    with the policy's side information (not in the paper)."""
    tau = o.guide_temperature
    task, estimate, extra = _environment(o, lo, lambda task, batch: -task.match_quality(batch) / tau)
    return task, estimate, {**extra, "guide_temperature": tau}


@register_method("rlsac", "RLSAC", checkpoint=True)
def _rlsac(o, device, lo=None):
    """The learned sampler of ``o.checkpoint`` in its own environment."""
    from rlsac.rl.checkpoint import check_reads, env_conf, load_actor, state_scales, task_options
    from rlsac.rl.rollout import in_channels, rlsac_estimate, with_lo
    from rlsac.tasks import task_for

    actor, ckpt_conf = load_actor(o.checkpoint, device)
    ckpt_conf = dict(ckpt_conf or {})
    task = task_for(o, task_options(ckpt_conf))
    check_reads(o.checkpoint, actor, in_channels(task), "rlsac")
    env = with_lo(env_conf(ckpt_conf, o.steps_per_episode), lo)
    # the policy sees residuals in its training unit, whatever threshold this evaluation scores with (issue #46);
    # a checkpoint from before state_scales sees them at the evaluation threshold, as the record was made: said here
    scales = state_scales(o.checkpoint, device, unit=float(task.threshold))
    eps = None if scales is None else scales["residual_threshold"]
    noted = eps is not None  # the fallback said once, when the evaluation runs (after every check: no note
    # before a later check's one error line)

    def estimate(batch, g):
        nonlocal noted
        if not noted:
            import sys

            noted = True
            print(f"note: {o.checkpoint} has no state_scales (written before them): its policy sees residuals at "
                  f"the evaluation threshold {float(task.threshold):g}, as the record's models were evaluated",
                  file=sys.stderr)
        return rlsac_estimate(task, batch, actor, o.iterations, env, sampling=o.sampling, generator=g,
                              policy_every=o.policy_every, sets_per_step=o.sets_per_step,
                              confidence=o.confidence, state_threshold=eps)

    extra = {"steps_per_episode": env.steps_per_episode}
    return task, estimate, extra if eps is None else {**extra, "state_threshold": eps}


@register_method("ngransac", "NG-RANSAC (ours, from the paper)", checkpoint=True)
def _ngransac(o, device, lo=None):
    """NG-RANSAC (rlsac.rl.ngransac): our RANSAC with minimal sets drawn from the network of ``o.checkpoint``."""
    from rlsac.rl.checkpoint import check_reads, task_options
    from rlsac.rl.ngransac import estimate, load
    from rlsac.tasks import task_for

    net, ckpt_conf = load(o.checkpoint, device)
    task = task_for(o, task_options(dict(ckpt_conf or {})))
    check_reads(o.checkpoint, net, task.feature_dim, "ngransac")
    return task, lambda batch, g: estimate(task, net, batch, o.iterations, g, lo=lo), {}


# ------------------------------------------------------------------------------ OpenCV
def _opencv(flag: str):
    """OpenCV's robust estimator of the task (its ``opencv_fit``) with method preset ``flag``."""
    def build(o, device, lo=None):
        import torch

        from rlsac.estimation.baselines import opencv_estimate
        from rlsac.tasks import opencv_threshold, task_for

        task = task_for(o)
        thr = opencv_threshold(o, task)

        def estimate(batch, g):
            seed = int(torch.randint(0, 2**31 - 1, (1,), generator=g, device=g.device).item())
            quality = task.match_quality(batch) if flag.startswith("prosac") else None
            return opencv_estimate(task, batch, flag, o.iterations, threshold=thr, seed=seed, quality=quality)

        return task, estimate, {}
    return build


# method name -> (rlsac.estimation.baselines.OPENCV_FLAGS preset, label); prosac orders the matches by match_quality
OPENCV_METHODS = {"opencv_ransac": ("ransac", "OpenCV RANSAC"), "usac": ("usac", "OpenCV USAC"),
                  "usac_accurate": ("usac_accurate", "OpenCV USAC_ACCURATE"), "magsac": ("magsac", "OpenCV MAGSAC++"),
                  "prosac": ("prosac", "OpenCV PROSAC (matches ordered by SNN)")}
# the no-LO arm (issue #26, rlsac.estimation.baselines.OPENCV_NOLO): the same samplers and scores without LO or polisher
OPENCV_METHODS.update({"usac-nolo": ("usac-nolo", "OpenCV USAC, no LO / polisher"),
                       "magsac-nolo": ("magsac-nolo", "OpenCV MAGSAC++, no LO / polisher"),
                       "prosac-nolo": ("prosac-nolo", "OpenCV PROSAC, no LO / polisher")})
for _name, (_flag, _label) in OPENCV_METHODS.items():
    register_method(_name, _label, needs="opencv_fit")(_opencv(_flag))


# ------------------------------------------------------------------------------ peers (issue #29)
def _peer(name: str):
    """A peer robust estimator (rlsac.estimation.baselines.PEERS) through the task's ``<name>_fit``."""
    def build(o, device, lo=None):
        import torch

        from rlsac.estimation.baselines import peer_estimate
        from rlsac.tasks import opencv_threshold, task_for

        task = task_for(o)
        thr = opencv_threshold(o, task)

        def estimate(batch, g):
            seed = int(torch.randint(0, 2**31 - 1, (1,), generator=g, device=g.device).item())
            return peer_estimate(task, batch, name, o.iterations, threshold=thr, seed=seed)

        return task, estimate, {}
    return build


register_method("degensac", "DEGENSAC (pydegensac; own LO)", needs="degensac_fit")(_peer("degensac"))
register_method("poselib", "PoseLib LO-RANSAC (own LO and bundle adjustment)", needs="poselib_fit")(_peer("poselib"))


# ------------------------------------------------------------------------------ local optimisation
def _with_lo(base: str):
    """The base method with local optimisation (rlsac.estimation.lo, the ``lo`` options); its LO budget is summed
    into the summary (CountingEstimate)."""
    def build(o, device, lo=None):
        from dataclasses import asdict

        from rlsac.estimation.lo import CountingEstimate, conf_for_method

        lo = conf_for_method(f"{base}-lo", o.lo)
        task, estimate, extra = METHODS[base].build(o.replace(method=base), device, lo)
        return task, CountingEstimate(estimate), {**extra, "lo": asdict(lo)}
    return build


for _base, _label in (("ransac", "RANSAC"), ("uniform", "Uniform"), ("guided", "Guided"),
                      ("rlsac", "RLSAC"), ("ngransac", "NG-RANSAC")):  # not in the paper: the same-LO arm (issue #26)
    register_method(f"{_base}-lo", f"{_label} + LO (not in the paper)", needs=METHODS[_base].needs,
                    checkpoint=METHODS[_base].checkpoint, lo=True)(_with_lo(_base))

LO_METHODS = tuple(m for m, spec in METHODS.items() if spec.lo)
