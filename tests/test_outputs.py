import pytest

from cystomap.outputs import atomic_dir, atomic_file


def test_atomic_dir_replaces_only_on_success(tmp_path):
    final = tmp_path / "stage"
    with atomic_dir(final) as tmp:
        (tmp / "a.txt").write_text("first")
    assert (final / "a.txt").read_text() == "first"

    with pytest.raises(RuntimeError), atomic_dir(final) as tmp:
        (tmp / "a.txt").write_text("partial")
        raise RuntimeError("boom")
    assert (final / "a.txt").read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stage"]

    with atomic_dir(final) as tmp:
        (tmp / "b.txt").write_text("second")
    assert sorted(p.name for p in final.iterdir()) == ["b.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stage"]


def test_atomic_file_leaves_no_partial_file(tmp_path):
    final = tmp_path / "out.json"
    with pytest.raises(ValueError), atomic_file(final) as tmp:
        tmp.write_text("{")
        raise ValueError
    assert list(tmp_path.iterdir()) == []
