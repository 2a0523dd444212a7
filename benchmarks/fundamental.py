"""Per-pair wall time of RLSAC vs OpenCV MAGSAC++ for fundamental matrices at the paper's 1k budget.

    python benchmarks/fundamental.py [--data data/fundamental/test.h5] [--pairs 16] [--iterations 1000]
                                     [--checkpoint CKPT] [--batch-pairs 8] [--device auto|cpu|cuda] [--threads 1]

RLSAC runs batched over pairs and episodes (``--batch-pairs`` pairs x ceil(iterations / 15) episodes per
forward pass); MAGSAC++ is OpenCV's ``USAC_MAGSAC`` through ``rlsac.baselines.opencv_fundamental``, one
pair at a time on one core. Both see the same first ``--pairs`` pairs of the prepared file (or synthetic
pairs when the file is missing). The reference (MAGSAC++) is measured in the same run; nothing is asserted.
Without ``--checkpoint`` the actor is randomly initialised: timing is representative, accuracy is not.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from rlsac.baselines import opencv_fundamental
from rlsac.evaluate import checkpoint_task_options, resolve_device, task_from
from rlsac.policy import Actor, PolicyConf
from rlsac.rollout import checkpoint_env, in_channels, load_actor, rlsac_estimate


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _data(path: str, pairs: int):
    """-> (data dict of numpy arrays, description); synthetic pairs when ``path`` is missing."""
    from rlsac.data import fundamental

    if Path(path).is_file():
        data, attrs = fundamental.read(path)
        data = {k: v[:pairs] for k, v in data.items()}
        return data, f"{path} ({attrs.get('scenes', '?')}), first {len(data['pair'])} pairs"
    sys.path.insert(0, str(Path(__file__).parent))
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
    ap.add_argument("--data", default="data/fundamental/test.h5")
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--batch-pairs", type=int, default=8, help="pairs per RLSAC forward batch")
    ap.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    from rlsac.data import fundamental

    data, what = _data(args.data, args.pairs)
    P = len(data["pair"])
    if args.checkpoint:
        actor, conf = load_actor(args.checkpoint, device)
        task = task_from("fundamental", checkpoint_task_options(dict(conf)))
        env_conf = checkpoint_env(dict(conf))
        who = args.checkpoint
    else:
        task = task_from("fundamental")
        torch.manual_seed(0)
        actor = Actor(in_channels(task), PolicyConf(graph_dims=4)).to(device).eval()
        env_conf, who = checkpoint_env({}), "randomly initialised actor (no --checkpoint)"
    episodes = -(-args.iterations // env_conf.steps_per_episode)
    print(f"device {device}, {torch.get_num_threads()} thread(s); data: {what}; {args.iterations} iterations; "
          f"actor: {who}")

    def run_rlsac(idx, seed=0):
        batch = fundamental.to_batch(data, idx, device=device)
        return rlsac_estimate(task, batch, actor, args.iterations, env_conf,
                              generator=torch.Generator(device=device).manual_seed(seed)), batch

    run_rlsac(list(range(min(2, P))))  # warm-up
    _sync(device)
    errs = {"rlsac": [], "magsac": []}
    t0 = time.perf_counter()
    for s in range(0, P, args.batch_pairs):
        idx = list(range(s, min(s + args.batch_pairs, P)))
        out, batch = run_rlsac(idx)
        _sync(device)
        errs["rlsac"].append((out, batch))
    t_rl = time.perf_counter() - t0

    t0 = time.perf_counter()
    for s in range(0, P, args.batch_pairs):
        idx = list(range(s, min(s + args.batch_pairs, P)))
        batch = fundamental.to_batch(data, idx)
        errs["magsac"].append((opencv_fundamental(batch, "magsac", args.iterations, seed=0), batch))
    t_mg = time.perf_counter() - t0

    print(f"\n{'method':10s} {'ms/pair':>9s} {'total s':>8s} {'mAA_R':>6s} {'mAA_t':>6s}")
    for name, t in (("rlsac", t_rl), ("magsac++", t_mg)):
        parts = errs["rlsac" if name == "rlsac" else "magsac"]
        e = {"err_R": [], "err_t": []}
        for out, batch in parts:
            np_batch = {k: (v.cpu().numpy() if torch.is_tensor(v) else v) for k, v in batch.items()}
            r = task.errors(*(x.cpu().numpy() if torch.is_tensor(x) else x
                              for x in (out["hyp"], out["valid"], out["inliers"])), np_batch)
            e["err_R"].append(r["err_R"])
            e["err_t"].append(r["err_t"])
        s = task.summarize({k: np.concatenate(v) for k, v in e.items()})
        print(f"{name:10s} {1e3 * t / P:9.2f} {t:8.3f} {s['mAA_R']:6.3f} {s['mAA_t']:6.3f}")
    print(f"ratio rlsac / magsac++ time per pair: {t_rl / t_mg:.1f}x "
          f"(rlsac: {args.batch_pairs} pairs x {episodes} episodes per batch; pose-error evaluation excluded)")


if __name__ == "__main__":
    main()
