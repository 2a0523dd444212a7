"""Datasets: synthetic lines, the CVPR 2020 tutorial layout, and the offline scene importer."""

from __future__ import annotations

import torch


def load(task: str, path, device: str | torch.device = "cpu", idx=slice(None)) -> dict:
    """Read a data file of task ``task`` (its registered reader) into the batch dict the task, env and
    baselines use."""
    return read_batch(task, path, device, idx)[0]


def read_batch(task: str, path, device: str | torch.device = "cpu", idx=slice(None)) -> tuple[dict, dict]:
    """``load``, with the file's attributes (and the reader's report of the instances it left out as unusable,
    attrs["unusable"]: rlsac.data.validity) -> (batch, attrs)."""
    from rlsac.tasks import task_class

    cls = task_class(task)
    arrays, attrs = cls.read(path)
    return cls.to_batch(arrays, idx, device), attrs


def n_unusable(attrs: dict) -> int:
    """How many instances of a file its reader left out as unusable (rlsac.data.validity), 0 when none."""
    return int((attrs.get("unusable") or {}).get("count", 0))


def slice_batch(batch: dict, idx) -> dict:
    """Rows ``idx`` (slice or index array) of every tensor / array in a batch dict."""
    out = {}
    for k, v in batch.items():
        out[k] = v[idx] if hasattr(v, "__getitem__") and not isinstance(v, (str, bytes)) else v
    return out
