"""The learner's positive control (issue #46, item 2d): can SAC learn a sampler when one input separates the inliers?

Synthetic pairs (rlsac.data.synthetic_pairs, ``snn="separable"``): the SNN channel puts every true inlier below 0.5 and
every outlier above, by construction. RLSAC trains with the fold recipe's sizes (16 episodes per step, batch 32,
300 transitions before the first update: folds.train.rlsac) and is measured on held-out pairs every ``every`` steps:
  * pi(inliers): the policy's probability mass on the true inliers at its first step (uniform: the inlier ratio;
    the guided sampler at T = 0.1 and the oracle put ~1 there);
  * mAA_R / mAA_t at ``iterations`` hypotheses, against uniform, guided and the oracle (the refit on the true inliers).
At each inlier ratio of ``inlier_ratios``: a uniform 8-point set is all inliers with probability r^8 (0.3: 7e-5,
0.6: 0.017), and RLSAC's reward (the inlier ratio of the set's hypothesis) says little about a set with one outlier,
so how fast the policy finds the separating input tells a defect of the learner from a reward too sparse to learn from.

params.yaml ``positive_control`` (`rlsac scale --stage control`, stage positive_control) -> reports/positive_control.md
and .json.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlsac.config import section
from rlsac.data import fundamental as fdata
from rlsac.data.synthetic_pairs import SyntheticPairsConf, generate
from rlsac.errors import RlsacError
from rlsac.estimation.baselines import finalize
from rlsac.io import atomic_path
from rlsac.progress import tqdm
from rlsac.rl.env import EnvConf, SampleConsensusEnv
from rlsac.rl.policy import PolicyConf
from rlsac.rl.rollout import in_channels, rlsac_estimate
from rlsac.rl.sac import SACAgent, SACConf, masked_policy, seed_everything, train_loop
from rlsac.tasks.fundamental import FundamentalTask

# key -> (type, range) for rlsac.config.check_value; a list's range is each element's (seeds: numpy's, SEED_RANGE)
KEYS = {"steps": (int, "[1, inf)"), "every": (int, "[1, inf)"), "iterations": (int, "[1, inf)"),
        "seeds": (list[int], "SEED_RANGE"), "inlier_ratios": (list[float], "(0, 1]"), "train_pairs": (int, "[1, inf)"),
        "test_pairs": (int, "[1, inf)")}


def conf(params: dict[str, Any]) -> dict[str, Any]:
    """params.yaml ``positive_control``, checked (every key required, no other; issue #64: a bool is not a step count,
    a float not a seed, and ``every`` past ``steps`` would measure nothing after step 0)."""
    from rlsac.config import SEED_RANGE, check_value

    c = section(params, "positive_control")
    if set(c) != set(KEYS):
        raise RlsacError(f"positive_control needs exactly {sorted(KEYS)} (missing "
                         f"{sorted(set(KEYS) - set(c))}, unknown {sorted(set(c) - set(KEYS), key=str)})")
    for key, (tp, spec) in KEYS.items():
        c[key] = check_value(f"positive_control.{key}", c[key], tp, SEED_RANGE if spec == "SEED_RANGE" else spec)
        if tp is not int and not c[key]:
            raise RlsacError(f"positive_control.{key} must be a non-empty list, got {c[key]!r}")
    if c["every"] > c["steps"]:
        raise RlsacError(f"positive_control.every {c['every']} is larger than positive_control.steps {c['steps']}: "
                         "nothing would be measured after step 0")
    return c


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
    out["uniform"]["pi_inliers"] = round(float(batch["inliers"].float().mean()), 4)
    guided = (torch.softmax(-snn / 0.1, -1) * batch["inliers"]).sum(-1).mean()
    out["guided (T=0.1)"]["pi_inliers"] = round(float(guided), 4)
    out["oracle"]["pi_inliers"] = 1.0
    return out


def _measure(agent: SACAgent, task, test: dict, iterations: int, seed: int, rows: list, step: int) -> dict:
    """The actor after ``step`` steps on the test pairs: a row of the curve (appended to ``rows``)."""
    agent.actor.eval()
    res = rlsac_estimate(task, test, agent.actor, iterations, generator=torch.Generator().manual_seed(7))
    rows.append({"seed": seed, "step": step, "updates": int(agent.n_updates),
                 "pi_inliers": round(inlier_mass(agent, task, test), 4), **scores(task, test, res)})
    agent.actor.train()
    return {}


def run(params: dict[str, Any], out: str | Path = "reports/positive_control", track: bool = False) -> dict[str, Any]:
    """Train and measure at every inlier ratio and seed; write <out>.md and <out>.json -> a summary (an MLflow run
    "positive control" in experiment ``scale`` with ``track``: a signal mid-training ends it KILLED)."""
    from rlsac.tracking import check_store, start_run

    c = conf(params)
    check_store(track, "scale")
    with start_run("scale", "positive control", params={k: str(v) for k, v in c.items()},
                   tags={"command": "scale", "benchmark": "positive_control"}, enabled=track) as mlrun:
        summary = _train_and_measure(c, Path(out))
        mlrun.metrics({f"pi_inliers_r{k}": v for k, v in summary["final"].items()})
        for f in summary["files"]:
            mlrun.artifact(f, "positive_control")
    return summary


def _train_and_measure(c: dict[str, Any], out: Path) -> dict[str, Any]:
    task = FundamentalTask()
    results = []
    for ratio in c["inlier_ratios"]:
        train = batch_of(generate(SyntheticPairsConf(n_pairs=c["train_pairs"], inlier_ratio=ratio, seed=11)))
        test = batch_of(generate(SyntheticPairsConf(n_pairs=c["test_pairs"], inlier_ratio=ratio, seed=12)))
        data = {"coords": train["coords"], "mask": train["mask"], "features": task.features(train)}
        curves = []
        for seed in tqdm(c["seeds"], desc=f"positive control, inlier ratio {ratio}", unit="seed"):
            gen = seed_everything(int(seed))
            sac = SACConf(total_steps=c["steps"], num_envs=16, batch_size=32, learning_starts=300)
            agent = SACAgent(in_channels(task), PolicyConf(graph_dims=4), sac)
            rows: list[dict] = []
            measure = functools.partial(_measure, agent, task, test, c["iterations"], int(seed), rows)
            measure(0)
            train_loop(agent, task, data, EnvConf(), 0, gen, log=lambda m, s: None, validate=measure,
                       val_every=c["every"])
            curves.append({"seed": int(seed), "rows": rows})  # no timings: a re-run must give the same bytes
        results.append({"inlier_ratio": ratio, "controls": controls(task, test, c["iterations"]), "curves": curves})
    with atomic_path(out.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps({"conf": c, "results": results}, indent=1) + "\n")
    with atomic_path(out.with_suffix(".md")) as tmp:
        tmp.write_text(markdown(c, results))
    return {"files": [str(out.with_suffix(".md")), str(out.with_suffix(".json"))],
            "final": {r["inlier_ratio"]: float(np.mean([cv["rows"][-1]["pi_inliers"] for cv in r["curves"]]))
                      for r in results}}


def markdown(c: dict, results: list[dict]) -> str:
    lines = ["# The learner's positive control (issue #46, item 2d)", "",
             "Generated by `rlsac scale --stage control` (stage `positive_control`, params.yaml `positive_control`; "
             "rlsac.experiments.positive_control). Synthetic pairs whose SNN channel separates the true inliers by "
             f"construction (150 points, 0.5 px noise; {c['train_pairs']} training pairs, {c['test_pairs']} test "
             "pairs); RLSAC trained with the fold recipe's sizes (16 episodes per step, batch 32, the first update "
             f"after 300 transitions), training seeds {', '.join(map(str, c['seeds']))}, measured on the test pairs "
             f"at {c['iterations']} hypotheses. π(inliers): the policy's probability mass on the true inliers at its "
             "first step. RLSAC rows: mean over the seeds [min, max].", ""]
    for r in results:
        lines += [f"## Inlier ratio {r['inlier_ratio']} (a uniform 8-set is all inliers with probability "
                  f"{r['inlier_ratio'] ** 8:.1e})", "", "| sampler | π(inliers) | mAA_R | mAA_t |",
                  "| --- | --- | --- | --- |"]
        for name, s in r["controls"].items():
            lines.append(f"| {name} | {s['pi_inliers']:.3f} | {s['mAA_R']:.3f} | {s['mAA_t']:.3f} |")
        for i, row in enumerate(r["curves"][0]["rows"]):
            col = np.array([[cv["rows"][i][k] for k in ("pi_inliers", "mAA_R", "mAA_t")] for cv in r["curves"]])
            upd = [cv["rows"][i]["updates"] for cv in r["curves"]]
            cells = " | ".join(f"{m:.3f} [{lo:.3f}, {hi:.3f}]"
                               for m, lo, hi in zip(col.mean(0), col.min(0), col.max(0), strict=True))
            lines.append(f"| RLSAC, step {row['step']} ({min(upd)}-{max(upd)} updates) | {cells} |")
        lines += [""]
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    from rlsac.config import read_params

    print(run(read_params(sys.argv[1] if len(sys.argv) > 1 else "params.yaml")))
