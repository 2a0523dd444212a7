"""The NG-RANSAC learner (`rlsac train --method ngransac`): Adam on the expected task loss of NG-RANSAC's sampling
network (rlsac.rl.ngransac: the network, its loss and sampler), on the shared harness (rlsac.learners.harness:
configuration, data, validation, selection, checkpoint format, MLflow), as RLSAC's learner is.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from rlsac.devices import resolve_device
from rlsac.errors import RlsacError
from rlsac.learners.harness import (
    TrainConf,
    load_data,
    logged_conf,
    register_learner,
    selection_score,
    stored_conf,
    task_experiment,
    validation_summary,
)
from rlsac.rl import checkpoint
from rlsac.rl.ngransac import KIND, estimate, loss, network, payload, set_losses
from rlsac.rl.sac import seed_everything
from rlsac.tracking import start_run


@register_learner("ngransac", sections=("ngransac",))
def train(conf: TrainConf, track: bool = True, snapshots: list | None = None) -> dict:
    """``rlsac train --method ngransac``: ``conf`` a checked TrainConf (rlsac.learners.harness.check; method
    "ngransac") -> the summary of ``rlsac.evaluation.train.train``. The kept network (``conf.out``) is the best
    validation under
    ``conf.selection`` (RLSAC's rule and signals), else the last; no training state file (no --resume), no
    snapshots."""
    if snapshots is not None:
        raise RlsacError("train: snapshots of every validated actor are RLSAC's training's "
                         "(rlsac.experiments.selection)")
    if conf.resume:
        raise RlsacError("ngransac training has no --resume (it keeps no training state)")
    ng = conf.ngransac
    if conf.threads > 0:
        torch.set_num_threads(conf.threads)
    device = resolve_device(conf.device)
    task, data, val, unusable = load_data(conf, device)
    data["features_net"] = data.pop("features")
    if ng.signal == "pose":  # a file without the ground truth the signal reads fails here, not at the first update
        from rlsac.estimation.sampling import uniform_minimal_sets

        first = _rows(data, torch.tensor([0]))
        try:
            set_losses(task, first, uniform_minimal_sets(first["mask"], task.sample_size, 1), "pose")
        except (KeyError, IndexError, ValueError, TypeError) as e:
            raise RlsacError(f"{conf.data}: no ground truth for the pose signal ({e.__class__.__name__}: {e})"
                             ) from None
    gen = seed_everything(conf.seed)
    if device.type != "cpu":
        gen = torch.Generator(device=device).manual_seed(conf.seed)
    net = network(task, conf.policy).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=ng.lr)
    conf_dict, out = stored_conf(conf), Path(conf.out)
    n_pairs = int(data["mask"].shape[0])
    best, history, kept = {"score": -1.0}, [], None  # as RLSAC's: every selection signal is >= 0

    def validate(step: int) -> dict:
        res = estimate(task, net, val, conf.val_iterations, torch.Generator(device=device).manual_seed(1234))
        summ = validation_summary(task, val, res)
        history.append({"step": step, **summ})
        return summ

    name = conf.run_name or f"train {conf.task} ngransac {out.stem} ({Path(conf.data).stem})"
    tags = {"command": "train", "method": KIND, **conf.tags, "out": str(out)}
    logged = logged_conf(conf_dict)
    with start_run(task_experiment(conf.task), name, logged, tags=tags, enabled=track) as run:
        run.metrics(unusable)
        t0 = time.time()
        for step in range(1, ng.steps + 1):
            rows = torch.randint(0, n_pairs, (min(ng.batch_size, n_pairs),), generator=gen, device=gen.device)
            objective, mean_loss = loss(task, net, _rows(data, rows.cpu()), ng.samples, ng.signal, gen, ng.hypotheses)
            opt.zero_grad(set_to_none=True)
            objective.backward()
            opt.step()
            run.metrics({"losses/ngransac_objective": objective.item(), "charts/train_loss": mean_loss.item()},
                        step=step)
            if val is not None and (step % conf.val_every == 0 or step == ng.steps):
                summ = validate(step)
                run.metrics(summ, step=step)
                score = summ[selection_score(conf.selection)]
                if conf.selection != "last" and score > best["score"]:
                    best.update(score=score, step=step, **summ)
                    kept = payload(net, conf_dict, task.feature_dim, step, summ, conf.selection, history)
        if kept is None:  # no validation, or selection "last": the final network
            kept = payload(net, conf_dict, task.feature_dim, ng.steps, history[-1] if history else {},
                           conf.selection, history)
        kept["history"] = list(history)
        checkpoint.write(out, kept)
        seconds = time.time() - t0
        run.metrics({"time/train_seconds": seconds})
        run.artifact(out, "checkpoint")
    return {"checkpoint": str(out), "method": KIND, "steps": ng.steps, "seconds": round(seconds, 1),
            "selection": conf.selection, "best_score": best["score"],
            "best_step": best.get("step"), "final_val": history[-1] if history else {},
            **{k.replace("/", "_"): v for k, v in unusable.items() if v}}


def _rows(batch: dict, rows: torch.Tensor) -> dict:
    """Rows ``rows`` (1-d long, on the CPU) of a batch: tensors indexed on their device, numpy arrays with numpy."""
    out = {}
    for key, v in batch.items():
        if torch.is_tensor(v):
            out[key] = v[rows.to(v.device)]
        elif isinstance(v, np.ndarray) and v.ndim > 0:
            out[key] = v[rows.numpy()]
        elif isinstance(v, list):
            out[key] = [v[i] for i in rows.tolist()]
        else:
            out[key] = v
    return out
