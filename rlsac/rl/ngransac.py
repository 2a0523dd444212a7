"""NG-RANSAC (Brachmann & Rother, ICCV 2019), written from the paper: a per-point network predicts sampling
weights, RANSAC draws its minimal sets from them, and the network learns from the expected task loss.

* Network: the RLSAC actor's EdgeConv backbone (``rlsac.rl.policy.Actor``, shape ``TrainConf.policy``) on the task's
  data features only (``task.features``: coordinates, SNN ratio and, as task options, the descriptors), no
  environment memory: one logit per point, p = softmax over the valid points.
* Test time (``estimate``): our batched ``rlsac.estimation.baselines.ransac`` with every minimal set drawn from p
without
  replacement (``rlsac.estimation.sampling.weighted_minimal_sets``): the same budget, scoring, LO arm and final refit as
  ``ransac``, which is its uniform control.
* Training (``loss``): per pair K samples, each a hypothesis pool H_k of M minimal sets drawn from p (one RANSAC
  run: its hypothesis with the most inliers is the one selected); the sample's loss l_k is that of the selected
  hypothesis: ``inliers`` (self-supervised, - its inlier ratio at the task's threshold) or ``pose`` (supervised, the
  task's ground-truth error, clipped at its mAA limit and divided by it). The gradient of the expected loss is the
  paper's, mean_k (l_k - b) grad log p(H_k), log p(H_k) = sum of its sets' log-probabilities, with the baseline
  b = mean_k l_k (the paper's variance reduction). M = 1 (an option, not the paper's) scores each set alone.
* Its training (Adam, ``rlsac train --method ngransac``) is the learner rlsac.learners.ngransac: validation and model
  selection as RLSAC's (the shared harness, rlsac.learners.harness: the fold's validation pairs only, the same
  selection signals); the checkpoint format is ``rlsac.rl.checkpoint``'s with kind "ngransac" (``payload``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from rlsac.errors import RlsacError

SIGNALS = ("inliers", "pose")
KIND = "ngransac"  # rlsac.rl.checkpoint kind of its checkpoints


@dataclass
class NGRansacConf:
    """``TrainConf.ngransac``: the training of ``rlsac train --method ngransac`` (its network: ``TrainConf.policy``)."""

    steps: int = 200  # Adam updates
    batch_size: int = 8  # training pairs per update, drawn at random (seeded)
    # K samples per pair and update (the baseline is their mean loss) and M minimal sets per sample (its hypothesis
    # pool: one RANSAC run, the loss its best hypothesis's): the authors' training script's defaults (ngransac_train_
    # e2e.py: samplecount 4, hyps 16; the paper does not give them). M = 1 scores each set alone: not the paper's
    samples: int = 4
    hypotheses: int = 16
    # Adam's learning rate: the paper fine-tunes a network initialised on inlier labels (a small rate); ours starts
    # from its random initialisation, whose logits are nearly equal (a probe on one fold's validation pairs, 150
    # updates: 1e-4 barely moved them, 3e-3 was unstable)
    lr: float = 1e-3
    # "inliers": self-supervised, - inlier ratio of each set's hypothesis; "pose": supervised, the task's error
    # against the ground truth (task.errors; clipped at the task's mAA limit, divided by it)
    signal: str = "inliers"

    ranges = {"steps": "[1, inf)", "batch_size": "[1, inf)", "samples": "[2, inf)", "hypotheses": "[1, inf)",
              "lr": "(0, inf)", "signal": SIGNALS}


def network(task, policy_conf):
    """The per-point sampling network of ``task``: the RLSAC actor's backbone on the task's data features.
    (B, N, task.feature_dim) features, (B, N) mask -> (B, N) logits, -inf on masked points."""
    from rlsac.rl.policy import Actor

    return Actor(task.feature_dim, policy_conf)


def logits_of(net, task, batch: dict) -> torch.Tensor:
    """The network's per-point logits of a batch -> (B, N); its features computed unless the batch has them."""
    feats = batch["features_net"] if "features_net" in batch else task.features(batch)
    if feats.dim() != 3 or feats.shape[:2] != batch["mask"].shape or feats.shape[-1] != task.feature_dim:
        raise RlsacError(f"ngransac: features {tuple(feats.shape)} must be (B, N, {task.feature_dim}) for mask "
                         f"{tuple(batch['mask'].shape)}")
    return net(feats, batch["mask"])


@torch.no_grad()
def estimate(task, net, batch: dict, iterations: int, generator: torch.Generator | None = None, lo=None) -> dict:
    """NG-RANSAC on a batch: ``iterations`` minimal sets drawn from the network's probabilities, scored, refit (and
    locally optimised with ``lo``) by ``rlsac.estimation.baselines.ransac``. batch: coords (B, N, d), mask (B, N), what
    ``task.features`` needs -> ransac's output (hyp, valid, inliers, best_count, hypotheses)."""
    from rlsac.estimation.baselines import ransac

    was_training = net.training
    net.eval()
    try:
        return ransac(task, batch, iterations, generator, lo=lo, logits=logits_of(net, task, batch))
    finally:
        net.train(was_training)


def set_losses(task, batch: dict, idx: torch.Tensor, signal: str) -> torch.Tensor:
    """The loss of each sampled minimal set's hypothesis (no gradient): ``pool_losses`` with pools of one set.
    idx (B, K, m) -> (B, K)."""
    return pool_losses(task, batch, idx[:, :, None], signal)


def pool_losses(task, batch: dict, idx: torch.Tensor, signal: str) -> torch.Tensor:
    """The loss of each hypothesis pool (no gradient): RANSAC on the pool's M minimal sets selects the hypothesis with
    the most inliers (the first on a tie), and the pool's loss is the selected hypothesis's.

    batch: coords (B, N, d), mask (B, N) (+ the ground truth ``task.errors`` reads for "pose"), idx (B, K, M, m)
    -> (B, K): "inliers": - inlier count / valid points (a pool of degenerate sets: 0); "pose": the task's error (the
    largest of its error components, e.g. max(err_R, err_t)) clipped at ``task.maa_limit_deg`` and divided by it,
    in [0, 1] (a pool of degenerate sets: 1)."""
    from rlsac.estimation.lo import score_sets
    from rlsac.estimation.sampling import gather_points

    if signal not in SIGNALS:
        raise RlsacError(f"ngransac signal must be one of {', '.join(SIGNALS)}, got {signal!r}")
    if idx.dim() != 4:
        raise ValueError(f"pool_losses: idx (B, K, M, m) expected, got {tuple(idx.shape)}")
    coords, mask = batch["coords"], batch["mask"]
    B, K, M, m = idx.shape
    with torch.no_grad():
        hyps, valid, res, count = score_sets(task, gather_points(coords, idx.reshape(B, K * M, m)), coords, mask)
        count = count.masked_fill(~valid, -1).view(B, K, M)  # a degenerate set is never selected over a valid one
        best_count, best = count.max(-1)  # (B, K): max over a dim returns the first maximum's index
        flat = torch.arange(K, device=best.device) * M + best  # the selected set, in (B, K * M)
        chosen_valid = valid.gather(1, flat)
        if signal == "inliers":
            ratio = best_count.clamp_min(0).to(coords.dtype) / mask.sum(-1, keepdim=True).clamp_min(1).to(coords.dtype)
            return -ratio.masked_fill(~chosen_valid, 0.0)
        pick = flat.flatten()
        rows = torch.arange(B, device=flat.device).repeat_interleave(K)
        hyp, res = hyps[rows, pick], res[rows, pick]  # (B * K, ...) selected hypotheses and their residuals
        inl = (res <= task.threshold) & mask.repeat_interleave(K, 0) & chosen_valid.flatten()[:, None]
        errs = task.errors(hyp.cpu().numpy(), chosen_valid.flatten().cpu().numpy(), inl.cpu().numpy(),
                           repeat_rows(batch, K))
        err = np.max(np.stack([np.asarray(e, np.float64) for e in errs.values()]), axis=0)
        limit = float(getattr(task, "maa_limit_deg", 1.0))
        loss = np.minimum(np.nan_to_num(err, nan=limit), limit) / limit
        return torch.as_tensor(loss, dtype=coords.dtype, device=coords.device).view(B, K)


def repeat_rows(batch: dict, k: int) -> dict:
    """Every row of a batch dict k times in a row (torch and numpy arrays; other values kept): row b*k + j is b."""
    B = batch["mask"].shape[0]
    out = {}
    for key, v in batch.items():
        if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == B:
            out[key] = v.repeat_interleave(k, 0)
        elif isinstance(v, np.ndarray) and v.ndim > 0 and v.shape[0] == B:
            out[key] = np.repeat(v, k, axis=0)
        else:
            out[key] = v
    return out


def loss(task, net, batch: dict, samples: int, signal: str, generator: torch.Generator | None = None,
         hypotheses: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """NG-RANSAC's surrogate objective on a batch and the samples' mean task loss.

    batch: coords (B, N, d), mask (B, N), the task's features -> (objective (), mean loss ()): K = ``samples``
    hypothesis pools of M = ``hypotheses`` minimal sets per pair drawn from the network's p, each pool's loss l that of
    its selected hypothesis (``pool_losses``); objective = mean_{b,k} (l_bk - mean_k l_bk) log p(H_bk), log p(H) the
    sum over its sets, whose gradient is the paper's estimate of the gradient of the expected loss E_{H ~ p}[l(H)]."""
    from rlsac.estimation.sampling import set_log_prob, weighted_minimal_sets

    mask = batch["mask"]
    if int(mask.sum(-1).min()) < task.sample_size:
        raise RlsacError(f"ngransac: a pair has fewer than {task.sample_size} valid points")
    logits = logits_of(net, task, batch)  # (B, N)
    B, K, M = logits.shape[0], samples, hypotheses
    idx = weighted_minimal_sets(logits, mask, task.sample_size, K * M, generator)  # (B, K * M, m)
    losses = pool_losses(task, batch, idx.view(B, K, M, -1), signal)  # (B, K)
    advantage = losses - losses.mean(-1, keepdim=True)  # the baseline: the pair's mean loss over its K samples
    log_p = set_log_prob(logits, mask, idx).view(B, K, M).sum(-1)  # log p(H_k): the pool's sets drawn independently
    return (advantage * log_p).mean(), losses.mean()


def payload(net, conf: dict, in_channels: int, step: int, val: dict, selection: str, history: list) -> dict:
    """The checkpoint dict of an NG-RANSAC network: ``rlsac.rl.checkpoint.actor_payload``'s with kind "ngransac"."""
    from rlsac.rl.checkpoint import actor_payload

    return {"kind": KIND, **actor_payload(net, conf, in_channels, step, val, selection, history)}


def load(path, device="cpu"):
    """An NG-RANSAC checkpoint -> (network in eval mode, training conf); RlsacError on a missing or bad file or on
    a checkpoint of another kind (an RLSAC actor)."""
    from rlsac.rl.checkpoint import load_actor

    return load_actor(path, device, kind=KIND)
