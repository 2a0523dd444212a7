"""RLSAC test-time cost on lines vs our RANSAC (before / after the issue #17 speed-ups), and training speed.

    python benchmarks/line_rollout.py [--instances 128] [--iterations 150] [--checkpoint checkpoints/line_o0.7.pt]
                                      [--batch 1,16,128] [--threads 1] [--compare-threads 1,2]
                                      [--train-steps 12] [--no-reference] [--device cpu]

1. Evaluation: ``--instances`` synthetic line instances (outlier rate ``--outlier-rate``, N = 100), run
   ``b`` instances per call for every ``b`` in ``--batch``: RLSAC after (the default ``rlsac_estimate``
   path with the evaluation defaults, params.yaml evaluate.line: ``--sets-per-step``, ``--confidence``),
   RLSAC paper setting (the same path, one set per step and the whole budget), RLSAC before
   (``reference=True``: the original per-step path; same seeds, its final hypotheses compared with the
   paper setting's) and our batched RANSAC at the same budget; ms per instance and the ratios.
   Then where RLSAC's time goes (model / selection / solver+scoring / state / refinement / other) at
   the smallest and largest batch, and RLSAC after / RANSAC at each of ``--compare-threads``.
2. Training: ``rlsac.rl.sac.train_loop`` for ``--train-steps`` vector-env steps with an update every step
   (lines: 32 envs, SAC batch 64; fundamental: synthetic pairs, N = 150, 264 channels, 16 envs, batch
   32, as in params.yaml), once with the networks' original forward pass (``reference_forward``) and
   once with the current one: steps per CPU second before and after.

Every ratio is measured in this one run; nothing is asserted. Without ``--checkpoint`` ('') the
actor is randomly initialised (timing representative, accuracy not).
"""

from __future__ import annotations

import argparse
import sys
from contextlib import nullcontext
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))

from timing import CLOCK, Clocks, Split, add_sampler_args, format_split, sampler_args  # noqa: E402

from rlsac.data import lines  # noqa: E402
from rlsac.estimation.baselines import ransac  # noqa: E402
from rlsac.evaluation.evaluate import resolve_device  # noqa: E402
from rlsac.rl import checkpoint  # noqa: E402
from rlsac.rl.env import EnvConf  # noqa: E402
from rlsac.rl.policy import Actor, PointNet, PolicyConf  # noqa: E402
from rlsac.rl.rollout import in_channels, rlsac_estimate  # noqa: E402
from rlsac.rl.sac import SACAgent, SACConf, train_loop  # noqa: E402
from rlsac.tasks.fundamental import FundamentalTask  # noqa: E402
from rlsac.tasks.line import LineTask  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--instances", type=int, default=128)
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--outlier-rate", type=float, default=0.5)
    ap.add_argument("--checkpoint", default="checkpoints/line_o0.7.pt")
    ap.add_argument("--batch", default="1,16,128", help="instances per rlsac_estimate / ransac call")
    ap.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--compare-threads", default="1,2", help="'' skips the thread comparison")
    ap.add_argument("--train-steps", type=int, default=12, help="0 skips the training benchmark")
    ap.add_argument("--no-reference", action="store_true")
    add_sampler_args(ap, "line")
    args = ap.parse_args()
    sampler_args(args, "line")
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    task = LineTask()
    n = args.instances
    data = lines.generate(lines.LineDataConf(outlier_rate=args.outlier_rate, n_instances=n, seed=7))
    if args.checkpoint:
        actor, conf = checkpoint.load_actor(args.checkpoint, device)
        env_conf, what = checkpoint.env_conf(conf), args.checkpoint
    else:
        torch.manual_seed(0)
        actor = Actor(in_channels(task), PolicyConf()).to(device).eval()
        env_conf, what = EnvConf(), "randomly initialised actor"
    episodes = -(-args.iterations // (env_conf.steps_per_episode * args.sets_per_step))
    batches = [int(b) for b in args.batch.split(",") if b]
    print(f"device {device}, {torch.get_num_threads()} thread(s); {n} instances x N=100, outlier rate "
          f"{args.outlier_rate}; {args.iterations} iterations ({episodes} episodes x {args.sets_per_step} sets per "
          f"step per instance after, confidence {args.confidence}); actor: {what}")

    def sync():
        if device == "cuda":
            torch.cuda.synchronize()

    def chunks(b):
        for s in range(0, n, b):
            yield s, lines.to_batch(data, slice(s, min(s + b, n)), device=device)

    def after(batch, g):
        return rlsac_estimate(task, batch, actor, args.iterations, env_conf, generator=g,
                              policy_every=args.policy_every, sets_per_step=args.sets_per_step,
                              confidence=args.confidence)

    def paper(batch, g):  # the same path with the paper's one set per step and whole budget
        return rlsac_estimate(task, batch, actor, args.iterations, env_conf, generator=g)

    def before(batch, g):
        return rlsac_estimate(task, batch, actor, args.iterations, env_conf, generator=g, reference=True)

    def ours_ransac(batch, g):
        return ransac(task, batch, args.iterations, g)

    b0 = lines.to_batch(data, slice(0, 2), device=device)  # warm-up
    for fn in (after, paper, before, ours_ransac):
        fn(b0, torch.Generator(device=device).manual_seed(0))

    print(f"\n== evaluation, CPU ms per instance ({n} instances, b per call; wall ms in brackets)")
    print(f"{'b':>5s} {'after':>17s} {'paper setting':>17s} {'before':>17s} {'ransac':>15s} {'after/ransac':>13s} "
          f"{'paper/ransac':>13s} {'before/ransac':>14s} {'before/after':>13s} {'same final hyp':>15s}")
    print("(same final hyp: paper setting vs before, the same function)")
    methods = {"after": after, "paper": paper, "ransac": ours_ransac}
    if not args.no_reference:
        methods["before"] = before
    splits, final = {}, {}
    for b in batches:
        clocks = {k: Clocks() for k in methods}
        sp = {k: Split(actor) for k in ("after", "paper", "before") if k in methods}
        outs = {k: [] for k in methods}
        for s, batch in chunks(b):  # interleaved call by call: the methods share the machine's load
            for name, fn in methods.items():
                g = torch.Generator(device=device).manual_seed(s)
                split = sp.get(name)
                with clocks[name], split or nullcontext(), split.timed() if split else nullcontext():
                    outs[name].append(fn(batch, g))
                    sync()
        c = {k: v.cpu for k, v in clocks.items()}
        w = {k: v.wall for k, v in clocks.items()}
        c.setdefault("before", float("nan"))
        w.setdefault("before", float("nan"))
        same = "-"
        if "before" in outs:
            pairs = zip(outs["paper"], outs["before"], strict=True)
            same = f"{sum(int((x['hyp'] == y['hyp']).all(-1).sum()) for x, y in pairs)}/{n}"
        cell = {k: f"{1e3 * c[k] / n:.2f} ({1e3 * w[k] / n:.1f})" for k in c}
        print(f"{b:5d} {cell['after']:>17s} {cell['paper']:>17s} {cell['before']:>17s} {cell['ransac']:>15s} "
              f"{c['after'] / c['ransac']:13.1f} {c['paper'] / c['ransac']:13.1f} {c['before'] / c['ransac']:14.1f} "
              f"{c['before'] / c['after']:13.2f} {same:>15s}")
        if b in (min(batches), max(batches)):
            splits.update({f"{k}, b={b}": v for k, v in sp.items()})
        final = outs
    errs = {}
    for name in ("after", "paper", "ransac"):
        hyp = torch.cat([o["hyp"] for o in final[name]]).cpu().numpy()
        valid = torch.cat([o["valid"] for o in final[name]]).cpu().numpy()
        errs[name] = task.summarize(task.errors(hyp, valid, None, data))["mAA"]
    print(f"mAA@0.5: rlsac after {errs['after']:.3f}, paper setting {errs['paper']:.3f}, ransac {errs['ransac']:.3f} "
          f"(hypotheses per instance: "
          f"{args.iterations} for both)")
    print()
    print(format_split(splits, n, "instance"))

    threads = [int(t) for t in args.compare_threads.split(",") if t]
    if threads and device == "cpu":
        b = min(max(batches), 32)
        print(f"\n== torch threads ({b} instances in one call), wall ms per instance (CPU time counts every thread)")
        print(f"{'threads':>7s} {'rlsac after':>12s} {'ransac':>8s}")
        batch = lines.to_batch(data, slice(0, b), device=device)
        for t in threads:
            torch.set_num_threads(t)
            clocks = {"after": Clocks(), "ransac": Clocks()}
            for _ in range(2):
                for name in clocks:
                    with clocks[name]:
                        methods[name](batch, torch.Generator(device=device).manual_seed(0))
            print(f"{t:7d} {1e3 * clocks['after'].wall / (2 * b):12.3f} {1e3 * clocks['ransac'].wall / (2 * b):8.3f}")
        torch.set_num_threads(args.threads)

    if args.train_steps > 0:
        print(f"\n== training: {args.train_steps} vector-env steps, one SAC update per step; steps per CPU second")
        print(f"{'task':12s} {'envs':>5s} {'batch':>6s} {'before steps/s':>15s} {'after steps/s':>14s} "
              f"{'after/before':>13s}")
        for name, tdata, tk, c, envs, bs in _train_setups(device):
            rate = {}
            for label, fwd in (("before", PointNet.reference_forward), ("after", PointNet.forward)):
                rate[label] = _train_rate(tk, tdata, c, envs, bs, args.train_steps, fwd, device)
            print(f"{name:12s} {envs:5d} {bs:6d} {rate['before']:15.2f} {rate['after']:14.2f} "
                  f"{rate['after'] / rate['before']:13.2f}")


def _train_setups(device):
    lt = LineTask()
    ld = lines.to_batch(lines.generate(lines.LineDataConf(outlier_rate=0.5, n_instances=64, seed=11)), device=device)
    yield "line", {"coords": ld["coords"], "mask": ld["mask"], "features": lt.features(ld)}, lt, PolicyConf(), 32, 64
    from fundamental_solvers import synthetic_batch

    fb = synthetic_batch(32)
    fb["features"][..., :4] = fb["coords"]
    g = torch.Generator().manual_seed(0)
    fb["features"][..., 4:] = torch.rand(fb["features"][..., 4:].shape, generator=g) * 0.2  # SIFT-like scale
    ft = FundamentalTask()
    fdata = {"coords": fb["coords"].to(device), "mask": fb["mask"].to(device), "features": ft.features(fb).to(device)}
    yield "fundamental", fdata, ft, PolicyConf(graph_dims=4), 16, 32


def _train_rate(task, tdata, pconf, envs, batch_size, steps, forward, device) -> float:
    """Vector-env steps per CPU second of train_loop with PointNet.forward replaced by ``forward``."""
    saved = PointNet.forward
    PointNet.forward = forward
    try:
        torch.manual_seed(0)
        sconf = SACConf(total_steps=steps + 1, num_envs=envs, batch_size=batch_size, learning_starts=envs,
                        buffer_size=20_000)
        agent = SACAgent(task.feature_dim + 3, pconf, sconf).to(device)
        gen = torch.Generator(device=device).manual_seed(0)
        buf = train_loop(agent, task, tdata, EnvConf(), 0, gen, log=lambda *a, **k: None)  # fills, first update
        t0 = CLOCK()
        agent.conf.total_steps = 2 * steps + 1
        train_loop(agent, task, tdata, EnvConf(), steps + 1, gen, log=lambda *a, **k: None, buffer=buf)
        return steps / (CLOCK() - t0)
    finally:
        PointNet.forward = saved


if __name__ == "__main__":
    main()
