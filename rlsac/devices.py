"""--device auto|cpu|cuda: the torch device (``resolve_device``) or its name (``device_name``)."""

from __future__ import annotations

import torch

from rlsac.errors import RlsacError


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RlsacError("--device cuda requested but no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise RlsacError(f"--device must be auto, cpu or cuda, got {name!r}")
    return torch.device(name)


def device_name(device: str | None) -> str:
    """"auto" (or None) -> "cuda" if available else "cpu"; "cuda" without a GPU is a user error."""
    return str(resolve_device((device or "auto").lower()))
