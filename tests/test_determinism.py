"""Outputs are a function of inputs, params and code: equal content gives equal bytes (issue #25).

A re-run of a DVC stage must leave git clean, so nothing in a committed file may depend on the time, a temporary
file name or the host."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from rlsac.reports import figfile  # noqa: E402
from rlsac.rl import checkpoint  # noqa: E402


def _payload() -> dict:
    g = torch.Generator().manual_seed(0)
    return {"actor": {"w": torch.randn(4, 3, generator=g), "b": torch.zeros(3)}, "conf": {"task": "line"},
            "in_channels": 3, "step": 7, "val": {"charts/val_mAA": 0.5}, "selection": "inlier_ratio", "history": []}


def test_checkpoint_bytes_do_not_depend_on_the_file_name(tmp_path):
    # torch.save(path) names its zip archive after the (random, temporary) file: the md5 changed on every write
    a, b = tmp_path / "a.pt", tmp_path / "sub" / "other_name.pt"
    checkpoint.write(a, _payload())
    checkpoint.write(b, _payload())
    assert a.read_bytes() == b.read_bytes() == checkpoint.to_bytes(_payload())
    assert torch.equal(checkpoint.read(b)["actor"]["w"], _payload()["actor"]["w"])
    assert not list(tmp_path.rglob("*.tmp"))  # the atomic write left nothing behind


def _figure():
    fig, ax = plt.subplots(figsize=(2, 2))
    ax.plot([0, 1, 2], [1, 0, 1], "o-")
    ax.set_title("same figure")
    return fig


def test_same_figure_same_bytes(tmp_path):
    # matplotlib stamps a PDF with its CreationDate unless told not to
    first = figfile.save(_figure(), tmp_path / "a", "f", dpi=50)
    second = figfile.save(_figure(), tmp_path / "b", "f", dpi=50)
    assert [p.rsplit(".", 1)[1] for p in first] == ["png", "pdf"]
    for p, q in zip(first, second, strict=True):
        assert open(p, "rb").read() == open(q, "rb").read()
    assert b"CreationDate" not in open(first[1], "rb").read()
