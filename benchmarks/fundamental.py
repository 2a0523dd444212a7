"""Per-pair time of RLSAC vs OpenCV MAGSAC++ (and our RANSAC) for fundamental matrices at the 1k budget.

    python benchmarks/fundamental.py [--data data/folds/hard/fountain/test.h5] [--pairs 12] [--iterations 1000]
                                     [--checkpoint checkpoints/folds/hard/fountain/rlsac.pt] [--batch-pairs 1,4]
                                     [--threads 1] [--device cpu] [--no-reference]

All methods see the same first ``--pairs`` pairs of the prepared file (synthetic pairs when it is
missing), in one process:

* RLSAC after: the default ``rlsac_estimate`` path with the evaluation defaults (params.yaml
  evaluate.fundamental: ``--sets-per-step``, ``--confidence``), one pair per call (what ``rlsac evaluate``
  does for named pairs), each pair seeded as ``rlsac evaluate`` seeds it;
* RLSAC paper setting: the same path with one minimal set per step and the whole budget (the paper's
  algorithm);
* RLSAC before: ``reference=True``, the original per-step path (the paper's algorithm as first written),
  same pairs and seeds; its final hypotheses are compared with the paper setting's (identical: the same
  function);
* OpenCV MAGSAC++ (``USAC_MAGSAC``, confidence 0.999, maxIters = ``--iterations``) and our batched
  RANSAC at the same budget, one pair at a time.

The methods run interleaved pair by pair at ``--threads`` torch and OpenCV threads; times are the
process's CPU time (wall time beside it; see ``timing.CLOCK``). Printed: ms per pair, hypotheses per
pair (RLSAC and RANSAC: counted; OpenCV: estimated from its termination rule, see
``timing.opencv_hypotheses``), the ratios to MAGSAC++, where RLSAC's time goes (model / selection /
solver+scoring / state / refinement / other) and how RLSAC's per-pair time scales with the pairs per
call (``--batch-pairs``). Nothing is asserted; all ratios come from this one run.
"""

from __future__ import annotations

import argparse
import sys
from contextlib import nullcontext
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))

from timing import Clocks, Split, add_sampler_args, format_split, opencv_hypotheses, sampler_args  # noqa: E402

from rlsac.estimation.baselines import opencv_estimate, ransac  # noqa: E402
from rlsac.evaluation.evaluate import pair_seed, resolve_device, task_from  # noqa: E402
from rlsac.rl import checkpoint  # noqa: E402
from rlsac.rl.policy import Actor, PolicyConf  # noqa: E402
from rlsac.rl.rollout import in_channels, rlsac_estimate  # noqa: E402
from rlsac.tasks.fundamental import FundamentalTask  # noqa: E402


def _data(path: str, pairs: int):
    """-> (data dict of numpy arrays, description); synthetic pairs when ``path`` is missing."""
    from rlsac.data import fundamental

    if Path(path).is_file():
        data, attrs = fundamental.read(path)
        data = {k: v[:pairs] for k, v in data.items()}
        return data, f"{path} ({attrs.get('scenes', '?')}), first {len(data['pair'])} pairs"
    from fundamental_solvers import synthetic_batch

    b = synthetic_batch(pairs)
    feats = np.zeros((pairs, b["coords"].shape[1], 261), np.float32)
    feats[..., :4] = b["coords"].numpy()
    data = {"coords": b["coords"].numpy(), "features": feats, "mask": b["mask"].numpy(), "K1": b["K1"],
            "K2": b["K2"], "dR": b["dR"], "dT": b["dT"], "size1": b["size1"].astype(np.int32),
            "size2": b["size2"].astype(np.int32), "pair": np.array([f"{i}" for i in range(pairs)], dtype=object),
            "scene": np.array(["synthetic"] * pairs, dtype=object)}
    return data, f"synthetic pairs ({path} missing), {pairs} pairs, 30% outliers"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/folds/hard/fountain/test.h5")
    ap.add_argument("--pairs", type=int, default=12)
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--checkpoint", default="checkpoints/folds/hard/fountain/rlsac.pt",
                    help="'' = a randomly initialised actor (same cost, meaningless accuracy)")
    ap.add_argument("--batch-pairs", default="1,4", help="pairs per RLSAC call for the scaling table")
    ap.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-reference", action="store_true", help="skip the reference (before) path")
    add_sampler_args(ap, "fundamental")
    args = ap.parse_args()
    sampler_args(args, "fundamental")
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    device = resolve_device(args.device)
    from rlsac.data import fundamental

    data, what = _data(args.data, args.pairs)
    P = len(data["pair"])
    if args.checkpoint:
        actor, conf = checkpoint.load_actor(args.checkpoint, device)
        task = task_from("fundamental", checkpoint.task_options(dict(conf)))
        env_conf = checkpoint.env_conf(dict(conf))
        who = args.checkpoint
    else:
        task = task_from("fundamental")
        torch.manual_seed(0)
        actor = Actor(in_channels(task), PolicyConf(graph_dims=4)).to(device).eval()
        env_conf, who = checkpoint.env_conf({}), "randomly initialised actor"
    episodes = -(-args.iterations // (env_conf.steps_per_episode * args.sets_per_step))
    print(f"device {device}, {torch.get_num_threads()} thread(s); data: {what}; {args.iterations} iterations "
          f"; RLSAC after: {episodes} episodes x {env_conf.steps_per_episode} steps x {args.sets_per_step} sets "
          f"per pair, confidence {args.confidence}; actor: {who}")

    def sync():
        if device == "cuda":
            torch.cuda.synchronize()

    def gen(p):
        return torch.Generator(device=device).manual_seed(pair_seed(0, data["scene"][p], data["pair"][p]))

    def run_rlsac(idx, reference, split=None, paper=False):
        batch = fundamental.to_batch(data, idx, device=device)
        with split.timed() if split else nullcontext():
            out = rlsac_estimate(task, batch, actor, args.iterations, env_conf, generator=gen(idx[0]),
                                 reference=reference, policy_every=1 if reference or paper else args.policy_every,
                                 sets_per_step=1 if reference or paper else args.sets_per_step,
                                 confidence=0.0 if reference or paper else args.confidence)
            sync()
        return out, batch

    def run_magsac(p):
        batch = fundamental.to_batch(data, [p])
        return opencv_estimate(FundamentalTask(), batch, "magsac", args.iterations, seed=0), batch

    def run_ransac(p):
        batch = fundamental.to_batch(data, [p], device=device)
        out = ransac(task, batch, args.iterations, gen(p))
        sync()
        return out, batch

    run_rlsac([0], False)  # warm-up
    run_rlsac([0], False, paper=True)
    run_rlsac([0], True)
    run_magsac(0)
    run_ransac(0)
    names = ["rlsac after", "rlsac paper setting", "rlsac before", "opencv magsac++", "ransac (ours)"]
    if args.no_reference:
        names.remove("rlsac before")
    clocks = {k: Clocks() for k in names}
    outs = {k: [] for k in names}
    splits = {k: Split(actor) for k in names if k.startswith("rlsac")}
    for p in range(P):  # methods interleaved pair by pair: they share the machine's load
        for name in names:
            with clocks[name]:
                if name.startswith("rlsac"):
                    with splits[name]:
                        outs[name].append(run_rlsac([p], name == "rlsac before", splits[name],
                                                    paper=name == "rlsac paper setting"))
                elif name.startswith("opencv"):
                    outs[name].append(run_magsac(p))
                else:
                    outs[name].append(run_ransac(p))
    hyps = {k: float(np.mean([o["hypotheses"] for o, _ in outs[k]])) for k in splits}
    hyps["opencv magsac++"] = float(np.mean([opencv_hypotheses(o["inliers"], b["mask"].numpy(), args.iterations)[0]
                                             for o, b in outs["opencv magsac++"]]))
    hyps["ransac (ours)"] = float(args.iterations)

    def maa(outs):
        e = {"err_R": [], "err_t": []}
        for out, batch in outs:
            np_batch = {k: (v.cpu().numpy() if torch.is_tensor(v) else v) for k, v in batch.items()}
            r = task.errors(*(x.cpu().numpy() if torch.is_tensor(x) else x
                              for x in (out["hyp"], out["valid"], out["inliers"])), np_batch)
            for k in e:
                e[k].append(r[k])
        return task.summarize({k: np.concatenate(v) for k, v in e.items()})

    ref = clocks["opencv magsac++"]
    print(f"\n{'method (1 pair/call)':22s} {'CPU ms/pair':>12s} {'x magsac++':>11s} {'wall ms/pair':>13s} "
          f"{'x magsac++':>11s} {'hyps/pair':>10s} {'mAA_R':>6s} {'mAA_t':>6s}")
    for name in names:
        c, s = clocks[name], maa(outs[name])
        print(f"{name:22s} {1e3 * c.cpu / P:12.2f} {c.cpu / ref.cpu:11.1f} {1e3 * c.wall / P:13.2f} "
              f"{c.wall / ref.wall:11.1f} {hyps[name]:10.0f} {s['mAA_R']:6.3f} {s['mAA_t']:6.3f}")
    print("(opencv hyps/pair: estimated from its confidence-0.999 termination bound and final inlier ratio; "
          f"it stops early and never spends the {args.iterations} budget on these pairs)")
    if "rlsac before" in outs:
        same = sum(torch.equal(a["hyp"], b["hyp"]) for (a, _), (b, _) in
                   zip(outs["rlsac paper setting"], outs["rlsac before"], strict=True))
        print(f"rlsac after vs before: {clocks['rlsac before'].cpu / clocks['rlsac after'].cpu:.2f}x less CPU time; "
              f"paper setting vs before: {clocks['rlsac before'].cpu / clocks['rlsac paper setting'].cpu:.2f}x, "
              f"identical final hypothesis on {same}/{P} pairs")
    print()
    print(format_split(splits, P, "pair"))

    print(f"\nrlsac after, pairs per call (scaling; {episodes} rows per pair):")
    print(f"{'pairs/call':>10s} {'CPU ms/pair':>9s} {'x magsac++':>11s}")
    for bp in [int(x) for x in args.batch_pairs.split(",") if x]:
        c = Clocks()
        with c:
            for s in range(0, P, bp):
                run_rlsac(list(range(s, min(s + bp, P))), False)
        print(f"{bp:10d} {1e3 * c.cpu / P:9.2f} {c.cpu / ref.cpu:11.1f}")


if __name__ == "__main__":
    main()
