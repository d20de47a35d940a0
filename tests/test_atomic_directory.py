"""A multi-file output directory is replaced whole, or not at all."""

import pytest

from src.io.atomic import atomic_directory


def test_directory_replaced_whole_and_stale_files_dropped(tmp_path):
    out = tmp_path / "prepared"
    out.mkdir()
    (out / "stale.pt").write_text("old run")
    with atomic_directory(out) as tmp:
        (tmp / "new.pt").write_text("new run")
    assert sorted(p.name for p in out.iterdir()) == ["new.pt"]
    assert [p.name for p in tmp_path.iterdir()] == ["prepared"]  # no temporary leftovers


def test_crash_keeps_the_previous_output(tmp_path):
    out = tmp_path / "prepared"
    out.mkdir()
    (out / "complete.pt").write_text("previous complete run")
    with pytest.raises(RuntimeError), atomic_directory(out) as tmp:
        (tmp / "half.pt").write_text("partial")
        raise RuntimeError("killed mid-way")
    assert [p.name for p in out.iterdir()] == ["complete.pt"]
    assert (out / "complete.pt").read_text() == "previous complete run"
    assert [p.name for p in tmp_path.iterdir()] == ["prepared"]
