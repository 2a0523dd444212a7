"""SAC updates per CPU second: the record's kernels against the fast ones, side by side in one run (issue #46, item 3).

Two agents with the same weights take the same batches (real transitions of the castle fold's training pairs, or
random states where the file is missing); the reference is ``kernels="aten"`` (the record's: ATen/MKL products),
the candidate ``kernels="onednn"`` (rlsac.kernels). Timed alternately, one update each in turn, so a busy machine
slows both alike; CPU time of this process, one thread. Before timing, the check: on one fixed batch both compute
the same losses (to float32 rounding), and after ``--check-updates`` updates on the same batches the same weights.

More data per update: the candidate's CPU time per update at larger batches (transitions learned from per CPU
second). ``--out FILE`` writes what it printed as JSON (reports/speed_training.json, which reports/scale.md quotes).

    python benchmarks/sac_update.py [--data data/folds/hard/castle/train.h5] [--updates 40] [--out FILE]
"""

from __future__ import annotations

# isort: off
import rlsac  # noqa: F401  (its numeric pins before torch)
# isort: on
import argparse
import copy
import json
import os
import time
from pathlib import Path

import torch

from rlsac.policy import PolicyConf, knn
from rlsac.rollout import in_channels
from rlsac.sac import SACAgent, SACConf
from rlsac.tasks.fundamental import FundamentalTask

B, N = 32, 150  # the fold recipe's batch of transitions and points per pair


def batches(path: str, n: int, gen: torch.Generator, channels: int, k: int, size: int = B) -> list[tuple]:
    """n batches (s, s2, mask, graph, action, reward, done): the file's pairs with random memory channels, or
    random data channels where the file is missing."""
    task = FundamentalTask()
    if Path(path).is_file():
        from rlsac.tasks import read_batch

        data, _ = read_batch("fundamental", path, "cpu")
        feats, mask = task.features(data), data["mask"]
    else:
        feats, mask = torch.randn(64, N, channels, generator=gen), torch.ones(64, N, dtype=torch.bool)
    out = []
    for _ in range(n):
        inst = torch.randint(feats.shape[0], (size,), generator=gen)
        x, m = feats[inst], mask[inst]
        mem, mem2 = torch.rand(size, x.shape[1], 3, generator=gen), torch.rand(size, x.shape[1], 3, generator=gen)
        graph = knn(x[..., :4], k, m)
        action = torch.multinomial(m.float(), task.sample_size, generator=gen)
        out.append((torch.cat([x, mem], -1), torch.cat([x, mem2], -1), m, graph, action,
                    torch.rand(size, generator=gen), (torch.rand(size, generator=gen) < 0.1).float()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/folds/hard/castle/train.h5")
    ap.add_argument("--updates", type=int, default=40, help="timed updates per agent")
    ap.add_argument("--check-updates", type=int, default=5)
    ap.add_argument("--batch-sizes", default="32,64,128", help="the candidate's batches for the data-per-update table")
    ap.add_argument("--out", default="", help="also write the results as JSON here")
    a = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    task, pconf = FundamentalTask(), PolicyConf(graph_dims=4)
    ref = SACAgent(in_channels(task), pconf, SACConf(batch_size=B)).set_kernels("aten")
    fast = copy.deepcopy(ref).set_kernels("onednn")
    gen = torch.Generator().manual_seed(0)
    data = batches(a.data, a.check_updates + a.updates, gen, in_channels(task), pconf.k)

    # the check: the same losses on the same fixed batch, then the same weights after the same updates
    worst = 0.0
    for b in data[: a.check_updates]:
        m_ref, m_fast = ref.update(*b), fast.update(*b)
        for key in ("losses/qf1", "losses/qf2", "losses/actor", "losses/alpha"):
            worst = max(worst, abs(m_ref[key] - m_fast[key]) / max(abs(m_ref[key]), 1e-6))
    with torch.no_grad():
        w_diff = max(float((p - q).abs().max()) for p, q in zip(ref.parameters(), fast.parameters(), strict=True))
    print(f"check: {a.check_updates} updates on the same batches: largest relative loss difference {worst:.1e}, "
          f"largest weight difference {w_diff:.1e}")
    if worst > 1e-4:
        raise SystemExit("the two kernels do not compute the same losses")

    t = {"aten": 0.0, "onednn": 0.0}
    for b in data[a.check_updates:]:
        for name, agent in (("aten", ref), ("onednn", fast)):
            t0 = time.process_time()
            agent.update(*b)
            t[name] += time.process_time() - t0
    n = a.updates
    print(f"SAC updates per CPU second, batch {B} x {N} points, one thread, {n} updates each, interleaved:")
    for name in t:
        print(f"  {name:7s} {n / t[name]:6.2f} updates/s  ({1000 * t[name] / n:.1f} ms each)")
    print(f"ratio onednn / aten: {t['aten'] / t['onednn']:.2f}x")

    per_batch = {}
    print("more data per update (onednn): batch, ms per update, transitions per CPU second")
    for size in [int(x) for x in a.batch_sizes.split(",") if x]:
        sized = batches(a.data, a.updates // 2 + 2, gen, in_channels(task), pconf.k, size)
        agent = copy.deepcopy(fast)
        agent.update(*sized[0])
        t0 = time.process_time()
        for b in sized[1:]:
            agent.update(*b)
        ms = 1000 * (time.process_time() - t0) / (len(sized) - 1)
        per_batch[size] = ms
        print(f"  {size:4d} {ms:7.1f} ms  {1000 * size / ms:7.0f} transitions/s")
    if a.out:
        from rlsac.io import atomic_path
        from rlsac.numerics import cpu_vendor, mode

        rec = {"what": "SAC updates per CPU second, one thread: the record's kernels (aten) against oneDNN's, "
                       "interleaved in one run (benchmarks/sac_update.py)",
               "cpu": cpu_vendor(), "numerics": mode(), "cores": os.cpu_count(), "batch": 32, "points": N,
               "updates": n, "ms_per_update": {k: round(1000 * v / n, 2) for k, v in t.items()},
               "updates_per_cpu_second": {k: round(n / v, 2) for k, v in t.items()},
               "ratio": round(t["aten"] / t["onednn"], 2),
               "check": {"updates": a.check_updates, "max_relative_loss_difference": worst,
                         "max_weight_difference": w_diff},
               "onednn_ms_per_update_by_batch": {str(k): round(v, 2) for k, v in per_batch.items()}}
        with atomic_path(a.out) as tmp:
            Path(tmp).write_text(json.dumps(rec, indent=2) + "\n")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
