"""Where a SAC training step's CPU time goes (issue #46, item 3): collection vs update, fixed vs redrawn episodes.

One step of ``rlsac.rl.sac.train_loop`` = one vector-env step of ``num_envs`` episodes (policy forward, minimal-set
selection, 8-point solves, scoring) + ``updates_per_step`` SAC updates of ``batch_size`` transitions (six network
passes: actor and target critics on s', critics and actor on s, three backward). Printed as CPU seconds per step and as
ratios to the update, all measured in this run, on one thread.

    python benchmarks/sac_profile.py --data data/folds/hard/castle/train.h5 --pool data/scale/castle/pool.h5
"""

from __future__ import annotations

# isort: off
import rlsac  # noqa: F401  (its numeric pins before torch)
# isort: on
import argparse
import time

import torch

from rlsac.rl.env import EnvConf, SampleConsensusEnv
from rlsac.rl.episodes import FixedPairs, RedrawnPairs, pool_tensors
from rlsac.rl.policy import PolicyConf
from rlsac.rl.rollout import in_channels
from rlsac.rl.sac import ReplayBuffer, SACAgent, SACConf, seed_everything
from rlsac.tasks import read_batch
from rlsac.tasks.fundamental import FundamentalTask


def cpu() -> float:
    return time.process_time()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/folds/hard/castle/train.h5")
    ap.add_argument("--pool", default="data/scale/castle/pool.h5", help="'' skips the redrawn episodes")
    ap.add_argument("--steps", type=int, default=40)
    a = ap.parse_args()
    torch.set_num_threads(1)
    task, conf = FundamentalTask(), SACConf(num_envs=16, batch_size=32)
    gen = seed_everything(0)
    agent = SACAgent(in_channels(task), PolicyConf(graph_dims=4), conf)
    data, _ = read_batch("fundamental", a.data, "cpu")
    data["features"] = task.features(data)
    sources = {"fixed": FixedPairs(task, data, agent.actor)}
    if a.pool:
        pool, _ = read_batch("fundamental", a.pool, "cpu")
        sources["redraw"] = RedrawnPairs(task, pool_tensors(pool, "cpu"), agent.actor, 150, True)
    env = SampleConsensusEnv(task, EnvConf(), training=True)
    times = {}
    for name, src in sources.items():
        buf = ReplayBuffer(2000, src.n_points, task.sample_size, torch.device("cpu"), extra=src.extra_width)
        t_collect = t_update = t_lookup = 0.0
        for _ in range(a.steps):
            t0 = cpu()
            inst = torch.randint(src.n_instances, (conf.num_envs,), generator=gen)
            batch, feats, graph, drawn = src.draw(inst, gen)
            state = env.reset(batch, feats, episodes=1, generator=gen)
            with torch.no_grad():
                idx = env.select(agent.actor(state, env.mask, graph), sample=True)
            mem = env.memory()
            reward, done, act = env.step(idx)
            buf.add(inst[act], mem[act], env.memory()[act], idx[act], reward[act], done[act],
                    None if drawn is None else drawn[act])
            t1 = cpu()
            b_inst, b_mem, b_mem2, b_a, b_r, b_d, b_extra = buf.sample(conf.batch_size, gen)
            x, m, g = src.lookup(b_inst, b_extra)
            t2 = cpu()
            agent.update(torch.cat([x, b_mem], -1), torch.cat([x, b_mem2], -1), m, g, b_a, b_r, b_d)
            t3 = cpu()
            t_collect, t_lookup, t_update = t_collect + t1 - t0, t_lookup + t2 - t1, t_update + t3 - t2
        times[name] = [t / a.steps for t in (t_collect, t_lookup, t_update)]
    ref = times["fixed"][2]
    print(f"CPU seconds per training step, one thread ({a.steps} steps each; ratio to the fixed arm's update):")
    for name, (c, lk, u) in times.items():
        print(f"  {name:7s} collection {c:.4f} ({c / ref:.2f}x)  batch rebuild {lk:.4f} ({lk / ref:.2f}x)  "
              f"update {u:.4f} ({u / ref:.2f}x)  -> {1 / (c + lk + u):.2f} steps per CPU second")


if __name__ == "__main__":
    main()
