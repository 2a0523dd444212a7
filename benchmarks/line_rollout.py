"""RLSAC test-time cost on lines vs our RANSAC, and SAC training throughput.

    python benchmarks/line_rollout.py [--instances 256] [--iterations 150] [--checkpoint CKPT]
                                      [--device auto|cpu|cuda] [--threads 1] [--train-steps 60]

1. Evaluation: ``--instances`` synthetic line instances (outlier rate 0.5, N = 100) in one batch,
   RLSAC at ``--iterations`` hypotheses (15-step episodes, so 10 episodes per instance at 150) and
   our batched RANSAC at the same budget on the same instances; per-instance wall time and the ratio.
2. Training: a short ``rlsac.sac.train_loop`` run (``--train-steps`` vector-env steps of
   ``--num-envs`` episodes, updates from step ``--learning-starts`` on): env transitions/s and
   SAC updates/s.

The reference (RANSAC) is measured in the same run; no timing is asserted anywhere. Without
``--checkpoint`` the actor is randomly initialised (the cost of a forward pass does not depend on
the weights, so the timing is representative; the accuracy is not).
"""

from __future__ import annotations

import argparse
import time

import torch

from rlsac.baselines import ransac
from rlsac.data import lines
from rlsac.env import EnvConf
from rlsac.evaluate import resolve_device
from rlsac.policy import Actor, PolicyConf
from rlsac.rollout import in_channels, load_actor, rlsac_estimate
from rlsac.sac import SACAgent, SACConf, train_loop
from rlsac.tasks.line import LineTask


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _time(fn, device: str, repeats: int) -> float:
    fn()  # warm-up (allocations, kernels)
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    _sync(device)
    return (time.perf_counter() - t0) / repeats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--instances", type=int, default=256)
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--steps-per-episode", type=int, default=15)
    ap.add_argument("--outlier-rate", type=float, default=0.5)
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--train-steps", type=int, default=60)
    ap.add_argument("--num-envs", type=int, default=32)
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--learning-starts", type=int, default=200, help="transitions before the first update")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    task = LineTask()
    conf = lines.LineDataConf(outlier_rate=args.outlier_rate, n_instances=args.instances, seed=7)
    data = lines.generate(conf)
    batch = lines.to_batch(data, device=device)
    if args.checkpoint:
        actor, _ = load_actor(args.checkpoint, device)
        what = args.checkpoint
    else:
        torch.manual_seed(0)
        actor = Actor(in_channels(task), PolicyConf()).to(device).eval()
        what = "randomly initialised actor (no --checkpoint)"
    episodes = -(-args.iterations // args.steps_per_episode)
    print(f"device {device}, {torch.get_num_threads()} thread(s); {args.instances} instances x N={conf.n_points}, "
          f"outlier rate {args.outlier_rate}; {args.iterations} iterations; actor: {what}")

    def run_rlsac():
        return rlsac_estimate(task, batch, actor, args.iterations, EnvConf(steps_per_episode=args.steps_per_episode),
                              generator=torch.Generator(device=device).manual_seed(0))

    def run_ransac():
        return ransac(task, batch, args.iterations, torch.Generator(device=device).manual_seed(0))

    t_rl = _time(run_rlsac, device, args.repeats)
    t_ra = _time(run_ransac, device, args.repeats)
    errs = {name: task.summarize(task.errors(o["hyp"].cpu().numpy(), o["valid"].cpu().numpy(), None, data))
            for name, o in (("rlsac", run_rlsac()), ("ransac", run_ransac()))}
    n = args.instances
    print(f"\n== evaluation ({n} instances x {episodes} episodes = {n * episodes} rows batched)")
    print(f"{'method':8s} {'ms/instance':>12s} {'batch s':>8s} {'mAA@0.5':>8s}")
    print(f"{'rlsac':8s} {1e3 * t_rl / n:12.3f} {t_rl:8.3f} {errs['rlsac']['mAA']:8.3f}")
    print(f"{'ransac':8s} {1e3 * t_ra / n:12.3f} {t_ra:8.3f} {errs['ransac']['mAA']:8.3f}")
    print(f"ratio rlsac / ransac time: {t_rl / t_ra:.1f}x")

    # ---- training throughput
    sconf = SACConf(total_steps=args.train_steps, num_envs=args.num_envs, batch_size=args.batch_size,
                    learning_starts=args.learning_starts, buffer_size=20_000)
    agent = SACAgent(in_channels(task), PolicyConf(), sconf).to(device)
    tdata = {"coords": batch["coords"], "mask": batch["mask"], "features": task.features(batch)}
    n_upd = [0]
    update = agent.update

    def counted_update(*a, **k):
        n_upd[0] += 1
        return update(*a, **k)

    agent.update = counted_update
    gen = torch.Generator(device=device).manual_seed(0)
    _sync(device)
    t0 = time.perf_counter()
    buf = train_loop(agent, task, tdata, EnvConf(steps_per_episode=args.steps_per_episode), 0, gen,
                     log=lambda *a, **k: None)
    _sync(device)
    dt = time.perf_counter() - t0
    trans = len(buf)
    print(f"\n== training ({args.train_steps} vector-env steps x {args.num_envs} envs, SAC batch {args.batch_size}, "
          f"updates after {args.learning_starts} transitions)")
    print(f"{trans} transitions, {n_upd[0]} updates in {dt:.2f} s: {trans / dt:.0f} transitions/s, "
          f"{n_upd[0] / dt:.1f} updates/s (collection and updates interleaved, as in training)")


if __name__ == "__main__":
    main()
