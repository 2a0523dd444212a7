"""Datasets: synthetic lines, the CVPR 2020 tutorial layout, and the offline scene importer."""

from __future__ import annotations

import torch

from rlsac.errors import RlsacError


def load(task: str, path, device: str | torch.device = "cpu", idx=slice(None)) -> dict:
    """Read a line or prepared two-view file into the batch dict the task, env and baselines use."""
    if task == "line":
        from rlsac.data import lines

        arrays, _ = lines.read(path)
        return lines.to_batch(arrays, idx, device)
    if task == "fundamental":
        from rlsac.data import fundamental

        arrays, _ = fundamental.read(path)
        return fundamental.to_batch(arrays, idx, device)
    raise RlsacError(f"unknown task '{task}' (known: line, fundamental)")


def batch_size(batch: dict) -> int:
    return int(batch["coords"].shape[0])


def slice_batch(batch: dict, idx) -> dict:
    """Rows ``idx`` (slice or index array) of every tensor / array in a batch dict."""
    out = {}
    for k, v in batch.items():
        out[k] = v[idx] if hasattr(v, "__getitem__") and not isinstance(v, (str, bytes)) else v
    return out
