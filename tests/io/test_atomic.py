"""atomic_output: the final name appears only on success; a failing body leaves nothing behind."""

from __future__ import annotations

import pytest

from mvtop_cli.io.atomic import atomic_output, atomic_path


def test_success_writes_the_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "track.mcap"
    with atomic_output(target) as fh:
        fh.write(b"abc")
        assert not target.exists()  # not visible under its final name while being written
    assert target.read_bytes() == b"abc"
    assert [p.name for p in tmp_path.iterdir()] == ["track.mcap"]


def test_body_that_raises_leaves_no_file(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_output(target, "w") as fh:
            fh.write("partial")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_failure_keeps_the_previous_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_output(target, "w") as fh:
            fh.write("new")
            raise KeyboardInterrupt
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    with atomic_output(target, "w") as fh:
        fh.write("new")
    assert target.read_text() == "new"


def test_atomic_path_for_writers_that_take_a_path(tmp_path):
    target = tmp_path / "a.bin"
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".a.bin.")
        tmp.write_bytes(b"1")
    assert target.read_bytes() == b"1"
    with pytest.raises(FileNotFoundError, match="nothing was written"):
        with atomic_path(tmp_path / "b.bin"):
            pass
    with pytest.raises(ValueError, match="mode must be"):
        with atomic_output(target, "a"):
            pass
