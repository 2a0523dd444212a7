"""The learner's positive control (issue #46, item 2d): can SAC learn a sampler when one input separates the inliers?

Synthetic pairs (rlsac.data.synthetic_pairs, ``snn="separable"``): the SNN channel puts every true inlier below 0.5 and
every outlier above, by construction. RLSAC trains with the fold recipe's sizes (16 episodes per step, batch 32,
300 transitions before the first update, params.yaml folds.train.rlsac) and is measured on held-out pairs after
every ``--every`` steps:
  * pi(inliers): the policy's probability mass on the true inliers at its first step (uniform = the inlier ratio;
    the guided sampler at T = 0.1 and the oracle put ~1 there);
  * mAA_R / mAA_t at ``--iterations`` hypotheses (the task's metric), against uniform, guided and the oracle (the
    refit on the true inliers).
If RLSAC stays near uniform here, the learner has a defect: real pairs cannot show anything before this passes.

    python benchmarks/positive_control.py --steps 600 --out reports/positive_control
"""

from __future__ import annotations

# isort: off
import rlsac  # noqa: F401  (its numeric pins before torch)
# isort: on
import argparse
import functools
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from rlsac.baselines import finalize
from rlsac.data import fundamental as fdata
from rlsac.data.synthetic_pairs import SyntheticPairsConf, generate
from rlsac.env import EnvConf, SampleConsensusEnv
from rlsac.io import atomic_path
from rlsac.policy import PolicyConf
from rlsac.rollout import in_channels, rlsac_estimate
from rlsac.sac import SACAgent, SACConf, masked_policy, seed_everything, train_loop
from rlsac.tasks.fundamental import FundamentalTask


def batch_of(arrays: dict) -> dict:
    b = fdata.to_batch(arrays)
    b["inliers"] = torch.from_numpy(arrays["inliers"])
    return b


@torch.no_grad()
def inlier_mass(agent: SACAgent, task, batch: dict, seed: int = 0) -> float:
    """Mean probability mass of the policy on the true inliers at its first step (after the random first set)."""
    env = SampleConsensusEnv(task, EnvConf(), training=False)
    feats = task.features(batch)
    state = env.reset(batch, feats, 1, generator=torch.Generator().manual_seed(seed))
    p, _ = masked_policy(agent.actor(state, env.mask, agent.actor.graph(feats, batch["mask"])), env.mask)
    return float((p * batch["inliers"]).sum(-1).mean())


def scores(task, batch: dict, res: dict) -> dict:
    errs = task.errors(res["hyp"].numpy(), res["valid"].numpy(), res["inliers"].numpy(),
                       {k: (v.numpy() if torch.is_tensor(v) else v) for k, v in batch.items()})
    s = task.summarize(errs)
    return {"mAA_R": round(s["mAA_R"], 4), "mAA_t": round(s["mAA_t"], 4)}


def controls(task, batch: dict, iterations: int) -> dict[str, dict]:
    g = lambda: torch.Generator().manual_seed(7)  # noqa: E731
    snn = task.match_quality(batch)
    out = {"uniform": scores(task, batch, rlsac_estimate(task, batch, None, iterations, generator=g())),
           "guided (T=0.1)": scores(task, batch, rlsac_estimate(task, batch, None, iterations, generator=g(),
                                                                 guide=-snn / 0.1)),
           "oracle": scores(task, batch, finalize(task, batch["coords"], batch["mask"],
                                                  *task.refine(batch["coords"], batch["inliers"])))}
    ratio = float(batch["inliers"].float().mean())
    out["uniform"]["pi_inliers"] = round(ratio, 4)
    out["guided (T=0.1)"]["pi_inliers"] = round(float((torch.softmax(-snn / 0.1, -1) * batch["inliers"]).sum(-1)
                                                      .mean()), 4)
    out["oracle"]["pi_inliers"] = 1.0
    return out


def _measure(agent: SACAgent, task, test: dict, iterations: int, seed: int, rows: list, step: int) -> dict:
    """The actor after ``step`` steps on the test pairs: a row of the curve (appended to ``rows``)."""
    agent.actor.eval()
    res = rlsac_estimate(task, test, agent.actor, iterations, generator=torch.Generator().manual_seed(7))
    row = {"seed": seed, "step": step, "updates": int(agent.n_updates),
           "pi_inliers": round(inlier_mass(agent, task, test), 4), **scores(task, test, res)}
    agent.actor.train()
    rows.append(row)
    print(json.dumps(row), file=sys.stderr, flush=True)
    return {}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=600, help="SAC steps (16 episodes each)")
    ap.add_argument("--every", type=int, default=100, help="measure every this many steps")
    ap.add_argument("--iterations", type=int, default=100, help="hypotheses per test pair")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="training seeds")
    ap.add_argument("--inlier-ratio", type=float, default=0.3, help="of the synthetic pairs (all-inlier 8-sets: r^8)")
    ap.add_argument("--out", default="reports/positive_control", help="writes <out>.md and <out>.json")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    task = FundamentalTask()
    train = batch_of(generate(SyntheticPairsConf(n_pairs=400, inlier_ratio=a.inlier_ratio, seed=11)))
    test = batch_of(generate(SyntheticPairsConf(n_pairs=150, inlier_ratio=a.inlier_ratio, seed=12)))
    data = {"coords": train["coords"], "mask": train["mask"], "features": task.features(train)}
    base = controls(task, test, a.iterations)
    curves = []
    for seed in a.seeds:
        gen = seed_everything(seed)
        conf = SACConf(total_steps=a.steps, num_envs=16, batch_size=32, learning_starts=300)
        agent = SACAgent(in_channels(task), PolicyConf(graph_dims=4), conf)
        rows: list[dict] = []
        measure = functools.partial(_measure, agent, task, test, a.iterations, seed, rows)
        t0 = time.process_time()
        measure(0)
        train_loop(agent, task, data, EnvConf(), 0, gen, log=lambda m, s: None, validate=measure, val_every=a.every)
        curves.append({"seed": seed, "cpu_s": round(time.process_time() - t0, 1), "rows": rows})
    write(a, base, curves)
    return 0


def write(a, base: dict, curves: list) -> None:
    out = Path(a.out)
    steps = [r["step"] for r in curves[0]["rows"]]
    lines = ["# The learner's positive control (issue #46, item 2d)", "",
             "Generated by `python benchmarks/positive_control.py " + " ".join(sys.argv[1:]) + "`. Synthetic pairs "
             "whose SNN channel separates the true inliers by construction (150 points, inlier ratio "
             f"{a.inlier_ratio}, 0.5 px noise; 400 training pairs, 150 test pairs); RLSAC trained with the fold "
             f"recipe's sizes (16 episodes per step, batch 32), {len(curves)} training seeds, measured on the test "
             f"pairs at {a.iterations} hypotheses.", "",
             "| sampler | π(inliers) | mAA_R | mAA_t |", "| --- | --- | --- | --- |"]
    for name, s in base.items():
        lines.append(f"| {name} | {s['pi_inliers']:.3f} | {s['mAA_R']:.3f} | {s['mAA_t']:.3f} |")
    for i, step in enumerate(steps):
        col = np.array([[c["rows"][i][k] for k in ("pi_inliers", "mAA_R", "mAA_t")] for c in curves])
        upd = [c["rows"][i]["updates"] for c in curves]
        mean, lo, hi = col.mean(0), col.min(0), col.max(0)
        cells = " | ".join(f"{m:.3f} [{lo_:.3f}, {hi_:.3f}]" for m, lo_, hi_ in zip(mean, lo, hi, strict=True))
        lines.append(f"| RLSAC, step {step} ({min(upd)}-{max(upd)} updates) | {cells} |")
    lines += ["", "RLSAC rows: mean over the training seeds [min, max]. CPU seconds per run: "
              + ", ".join(str(c["cpu_s"]) for c in curves) + "."]
    with atomic_path(out.with_suffix(".md")) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    with atomic_path(out.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps({"controls": base, "curves": curves}, indent=1) + "\n")
    print(f"wrote {out.with_suffix('.md')} and {out.with_suffix('.json')}")


if __name__ == "__main__":
    sys.exit(main())
