"""Files written atomically (temp file + rename, :func:`dibrpp.io.atomic_path`, which every datagen writer
uses) get the permissions of normally written files: 0o666 less the umask, not mkstemp's 0600."""
import os
import stat

import numpy as np
import pytest

from dibrpp.io import atomic_path, write_exr, write_png


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture
def umask():
    """Set the process umask for one test, then restore it."""
    old = os.umask(0o022)
    try:
        yield lambda mask: os.umask(mask)
    finally:
        os.umask(old)


@pytest.mark.parametrize("mask,expected", [(0o022, 0o644), (0o027, 0o640), (0o002, 0o664)])
def test_atomic_files_follow_the_umask(tmp_path, umask, mask, expected):
    umask(mask)
    with atomic_path(tmp_path / "record.json") as tmp:
        tmp.write_text("{}")
    write_png(tmp_path / "image.png", np.zeros((2, 2, 3), np.float32))
    write_exr(tmp_path / "image.exr", np.zeros((2, 2, 3), np.float32))
    plain = tmp_path / "plain.txt"
    plain.write_text("written the ordinary way")
    assert _mode(plain) == expected
    for name in ("record.json", "image.png", "image.exr"):
        assert _mode(tmp_path / name) == expected, name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["image.exr", "image.png", "plain.txt", "record.json"]


def test_a_failed_write_leaves_neither_file_nor_temp(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "x.json") as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []
