"""Datasets: synthetic lines, the CVPR 2020 tutorial layout, and the offline scene importer."""

from __future__ import annotations

import torch


def load(task: str, path, device: str | torch.device = "cpu", idx=slice(None)) -> dict:
    """Read a data file of task ``task`` (its registered reader) into the batch dict the task, env and
    baselines use."""
    from rlsac.tasks import task_class

    cls = task_class(task)
    arrays, _ = cls.read(path)
    return cls.to_batch(arrays, idx, device)


def slice_batch(batch: dict, idx) -> dict:
    """Rows ``idx`` (slice or index array) of every tensor / array in a batch dict."""
    out = {}
    for k, v in batch.items():
        out[k] = v[idx] if hasattr(v, "__getitem__") and not isinstance(v, (str, bytes)) else v
    return out
