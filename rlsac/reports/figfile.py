"""Writing a figure: PNG + PDF, atomically, with the same bytes for the same figure (no timestamp)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from rlsac.io import atomic_path  # noqa: E402


def save(fig, out_dir: Path, name: str, dpi: int) -> list[str]:
    """``<out_dir>/<name>.{png,pdf}`` -> their paths; closes ``fig``. The PDF's CreationDate is left out (matplotlib
    stamps the time otherwise), so a re-run of a figure stage leaves git clean."""
    paths = []
    for ext in ("png", "pdf"):
        path = Path(out_dir) / f"{name}.{ext}"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=ext, dpi=dpi if ext == "png" else None, bbox_inches="tight",
                        metadata={"CreationDate": None} if ext == "pdf" else None)
        paths.append(str(path))
    plt.close(fig)
    return paths
