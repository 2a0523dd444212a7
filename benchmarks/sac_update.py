"""SAC updates per CPU second: the record's kernels against the fast ones, side by side in one run (issue #46, item 3).

Agents with the same weights take the same batches (real transitions of the castle fold's training pairs, or random
states where the file is missing). The reference is the record's kernels (``aten`` products, ``eager`` neighbour
max: the update as the issue found it); the arms: ``onednn`` products (rlsac.rl.kernels), the ``compiled`` neighbour
max with the record's products, and both. Timed alternately, one update each in turn, so a busy machine slows all
alike; CPU time of this process, one thread. Before timing, the checks: on the same batches every arm computes the
reference's losses (to float32 rounding); a ``compiled`` arm leaves the very bytes of its eager twin's weights.

Then what bounds it: the update's dense-product FLOPs (torch's flop counter), oneDNN's product rate on this core
for the update's largest product and a large square one (measured here), and so the products' floor in ms and the
most any kernel choice could gain over the reference on this core.

More data per update: the fastest arm's CPU time per update at larger batches (transitions learned from per CPU
second). ``--out FILE`` writes what it printed as JSON (reports/speed_training.json, which docs/speed.md quotes).

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

from rlsac.rl.kernels import linear_for
from rlsac.rl.policy import PolicyConf, knn
from rlsac.rl.rollout import in_channels
from rlsac.rl.sac import SACAgent, SACConf
from rlsac.tasks.fundamental import FundamentalTask

B, N = 32, 150  # the fold recipe's batch of transitions and points per pair
# arm -> (products, neighbour max); the first is the reference
ARMS = {"aten": ("aten", "eager"), "onednn": ("onednn", "eager"), "aten+compiled": ("aten", "compiled"),
        "onednn+compiled": ("onednn", "compiled")}


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


def product_rate(shape: tuple[int, int, int], seconds: float = 1.0) -> float:
    """oneDNN's GFLOP per CPU second on one (rows, in) x (in, out) product, one thread, here."""
    rows, cin, cout = shape
    x, w = torch.randn(rows, cin), torch.randn(cout, cin)
    lin = linear_for("onednn")
    lin(x, w)
    n, t0 = 0, time.process_time()
    while time.process_time() - t0 < seconds:
        lin(x, w)
        n += 1
    return 2 * rows * cin * cout * n / (time.process_time() - t0) / 1e9


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/folds/hard/castle/train.h5")
    ap.add_argument("--updates", type=int, default=40, help="timed updates per agent")
    ap.add_argument("--check-updates", type=int, default=5)
    ap.add_argument("--batch-sizes", default="32,64,128", help="the fastest arm's batches (data per update)")
    ap.add_argument("--out", default="", help="also write the results as JSON here")
    a = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    task, pconf = FundamentalTask(), PolicyConf(graph_dims=4)
    base = SACAgent(in_channels(task), pconf, SACConf(batch_size=B))
    agents = {name: copy.deepcopy(base).set_kernels(*kern) for name, kern in ARMS.items()}
    gen = torch.Generator().manual_seed(0)
    data = batches(a.data, a.check_updates + a.updates, gen, in_channels(task), pconf.k)

    # the checks: the reference's losses on the same batches; a compiled arm its eager twin's bytes
    worst = dict.fromkeys(ARMS, 0.0)
    for b in data[: a.check_updates]:  # (also the compiled kernels' first calls: compilation is not timed)
        m = {name: agent.update(*b) for name, agent in agents.items()}
        for name in ARMS:
            for key in ("losses/qf1", "losses/qf2", "losses/actor", "losses/alpha"):
                ref = m["aten"][key]
                worst[name] = max(worst[name], abs(m[name][key] - ref) / max(abs(ref), 1e-6))
    same_bytes = {name: all(torch.equal(p, q) for p, q in zip(agents[name].parameters(),
                                                              agents[name.split("+")[0]].parameters(), strict=True))
                  for name in ARMS if name.endswith("+compiled")}
    print(f"check: {a.check_updates} updates on the same batches; largest relative loss difference to aten: "
          + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
    print("  compiled neighbour max, the same weight bytes as its eager twin: "
          + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in same_bytes.items()))
    if max(worst.values()) > 1e-4 or not all(same_bytes.values()):
        raise SystemExit("the arms do not compute the same update")

    t = dict.fromkeys(ARMS, 0.0)
    for b in data[a.check_updates:]:
        for name, agent in agents.items():
            t0 = time.process_time()
            agent.update(*b)
            t[name] += time.process_time() - t0
    n = a.updates
    ms = {name: 1000 * v / n for name, v in t.items()}
    print(f"SAC updates per CPU second, batch {B} x {N} points, one thread, {n} updates each, interleaved:")
    for name in t:
        print(f"  {name:16s} {n / t[name]:6.2f} updates/s  ({ms[name]:6.1f} ms each)  {ms['aten'] / ms[name]:.2f}x")
    fastest = min(ms, key=ms.get)

    # the bound: the update's products at oneDNN's best rate on this core
    from torch.utils.flop_counter import FlopCounterMode

    counter = copy.deepcopy(base)  # ATen's products: the ones torch's flop counter knows
    with FlopCounterMode(display=False) as fc:
        counter.update(*data[0])
    gflop = fc.get_total_flops() / 1e9
    shapes = {"update's first layer": (B * N, in_channels(task), 2 * pconf.widths[0]), "square 2048": (2048,) * 3}
    rates = {name: product_rate(shape) for name, shape in shapes.items()}
    floor = 1000 * gflop / max(rates.values())
    print(f"what bounds it: {gflop:.2f} GFLOP of dense products per update; oneDNN here "
          + ", ".join(f"{v:.0f} GFLOP/s ({k})" for k, v in rates.items())
          + f": the products alone take >= {floor:.1f} ms, so no choice of kernels gets past "
          f"{ms['aten'] / floor:.1f}x the reference on this core; the fastest arm spends "
          f"{ms[fastest] - floor:.1f} ms beyond that floor")

    per_batch = {}
    print(f"more data per update ({fastest}): batch, ms per update, transitions per CPU second")
    for size in [int(x) for x in a.batch_sizes.split(",") if x]:
        sized = batches(a.data, a.updates // 2 + 2, gen, in_channels(task), pconf.k, size)
        agent = copy.deepcopy(agents[fastest])
        agent.update(*sized[0])
        t0 = time.process_time()
        for b in sized[1:]:
            agent.update(*b)
        per = 1000 * (time.process_time() - t0) / (len(sized) - 1)
        per_batch[size] = per
        print(f"  {size:4d} {per:7.1f} ms  {1000 * size / per:7.0f} transitions/s")
    if a.out:
        from rlsac.io import atomic_path
        from rlsac.numerics import cpu_vendor, mode

        rec = {"what": "SAC updates per CPU second, one thread: the record's kernels (aten products, eager neighbour "
                       "max) against oneDNN's products and the compiled neighbour max, interleaved in one run "
                       "(benchmarks/sac_update.py)",
               "cpu": cpu_vendor(), "numerics": mode(), "cores": os.cpu_count(), "batch": B, "points": N,
               "updates": n, "arms": {k: list(v) for k, v in ARMS.items()},
               "ms_per_update": {k: round(v, 2) for k, v in ms.items()},
               "updates_per_cpu_second": {k: round(n / v, 2) for k, v in t.items()},
               "ratio_to_aten": {k: round(ms["aten"] / v, 2) for k, v in ms.items()},
               "check": {"updates": a.check_updates, "max_relative_loss_difference": worst,
                         "compiled_same_bytes_as_eager": same_bytes},
               "bound": {"gflop_per_update": round(gflop, 3), "onednn_gflop_per_s": {k: round(v, 1) for k, v in
                                                                                      rates.items()},
                         "products_floor_ms": round(floor, 1), "max_ratio_to_aten": round(ms["aten"] / floor, 2)},
               "fastest": fastest,
               "fastest_ms_per_update_by_batch": {str(k): round(v, 2) for k, v in per_batch.items()}}
        with atomic_path(a.out) as tmp:
            Path(tmp).write_text(json.dumps(rec, indent=2) + "\n")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
