"""Datasets: synthetic lines, the CVPR 2020 tutorial layout, and the offline scene importer (a task reads its files
into a batch: rlsac.tasks.read_batch)."""

from __future__ import annotations


def n_unusable(attrs: dict) -> int:
    """How many instances of a file its reader left out as unusable (rlsac.data.validity), 0 when none."""
    return int((attrs.get("unusable") or {}).get("count", 0))


def slice_batch(batch: dict, idx) -> dict:
    """Rows ``idx`` (slice or index array) of every tensor / array in a batch dict."""
    out = {}
    for k, v in batch.items():
        out[k] = v[idx] if hasattr(v, "__getitem__") and not isinstance(v, (str, bytes)) else v
    return out
