"""rlsac.io: atomic writes, alone and as one all-or-nothing set of outputs."""

from __future__ import annotations

import pytest

from rlsac.errors import RlsacError
from rlsac.io import all_or_nothing, staged, write_text


def test_all_or_nothing_renames_every_output_when_the_block_succeeds(tmp_path):
    a, b = tmp_path / "a.md", tmp_path / "sub" / "b.csv"
    a.write_text("old a")
    with all_or_nothing():
        write_text(a, "new a")
        write_text(b, "new b")
        assert a.read_text() == "old a" and not b.exists()  # nothing in place before the block ends
        assert staged(a).read_text() == "new a" and staged(a) != a  # what the block wrote is readable
        write_text(a, "newer a")
        assert staged(a).read_text() == "newer a"  # the latest write of a path
    assert a.read_text() == "newer a" and b.read_text() == "new b"
    assert staged(a) == a and not list(tmp_path.rglob("*.tmp"))


def test_all_or_nothing_writes_nothing_when_the_block_fails(tmp_path):
    a, b = tmp_path / "a.md", tmp_path / "b.md"
    a.write_text("old a")
    with pytest.raises(ValueError):
        with all_or_nothing():
            write_text(a, "new a")
            write_text(b, "new b")
            raise ValueError("a record was bad half-way")
    assert a.read_text() == "old a" and not b.exists() and not list(tmp_path.rglob("*.tmp"))


def test_all_or_nothing_refuses_a_folder_in_the_way_before_renaming_any(tmp_path):
    a, way = tmp_path / "a.md", tmp_path / "z.json"
    a.write_text("old a")
    way.mkdir()
    with pytest.raises(RlsacError, match="z.json: a folder of that name is in the way"):
        with all_or_nothing():
            write_text(a, "new a")
            write_text(way, "{}")
    assert a.read_text() == "old a" and way.is_dir() and not list(tmp_path.rglob("*.tmp"))


def test_nested_blocks_are_decided_by_the_outer_one(tmp_path):
    a = tmp_path / "a.md"
    with pytest.raises(ValueError):
        with all_or_nothing():
            with all_or_nothing():
                write_text(a, "inner")
            assert not a.exists()
            raise ValueError
    assert not a.exists() and not list(tmp_path.rglob("*.tmp"))
