"""parq_runtime.files: outputs are whole or absent, inputs fail with one line."""
import os

import pytest

from parq_runtime import files
from parq_runtime.errors import ParqError


def contents(folder):
    return {p.name: p.read_text() for p in folder.iterdir()}


def test_atomic_folder_creates_and_replaces(tmp_path):
    out = tmp_path / "out"
    with files.atomic_folder(out, "a test folder") as tmp:
        assert tmp.parent == tmp_path and tmp != out and not out.exists()
        (tmp / "a.txt").write_text("first")
    assert contents(out) == {"a.txt": "first"}
    assert oct(out.stat().st_mode & 0o777) == oct(0o777 & ~files.umask())
    with files.atomic_folder(out, "a test folder") as tmp:
        (tmp / "b.txt").write_text("second")
    assert contents(out) == {"b.txt": "second"}
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_atomic_folder_failure_keeps_the_old_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old")
    with pytest.raises(RuntimeError, match="boom"):
        with files.atomic_folder(out, "a test folder") as tmp:
            (tmp / "a.txt").write_text("half")
            raise RuntimeError("boom")
    assert contents(out) == {"a.txt": "old"}
    with pytest.raises(ParqError, match=r"out: could not write a test folder \(.*\)"):
        with files.atomic_folder(out, "a test folder") as tmp:
            raise OSError(28, "No space left on device")
    assert contents(out) == {"a.txt": "old"}
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_atomic_folder_puts_the_old_folder_back_when_the_swap_fails(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old")
    real_replace = os.replace

    def replace(src, dst):
        if str(src).endswith(".tmp"):       # the new folder cannot be moved into place
            raise OSError(18, "Invalid cross-device link")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(ParqError, match="could not write"):
        with files.atomic_folder(out, "a test folder") as tmp:
            (tmp / "a.txt").write_text("new")
    assert contents(out) == {"a.txt": "old"}
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_atomic_folder_names_an_unwritable_parent(tmp_path):
    with pytest.raises(ParqError, match="cannot write there"):
        with files.atomic_folder(tmp_path / "missing" / "out", "a test folder"):
            pass


def test_read_json_one_line_errors(tmp_path):
    with pytest.raises(ParqError, match="not found"):
        files.read_json(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ParqError, match="bad.json: not readable JSON"):
        files.read_json(tmp_path / "bad.json")
    (tmp_path / "ok.json").write_text('{"a": 1}')
    assert files.read_json(tmp_path / "ok.json") == {"a": 1}


def test_staged_files_appear_together_or_not_at_all(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.ply"
    with pytest.raises(ParqError, match="later step"):
        with files.staged_files() as stage:
            stage(a, "{}\n")
            stage(b, b"ply\n")
            raise ParqError("a later step failed")
    assert list(tmp_path.iterdir()) == []       # neither output, no temporary file
    with files.staged_files() as stage:
        stage(a, "{}\n")
        stage(b, b"ply\n")
        assert not a.exists() and not b.exists()    # renamed into place only at the end
    assert a.read_text() == "{}\n" and b.read_bytes() == b"ply\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.ply"]


def test_staged_file_that_cannot_be_created_is_one_line(tmp_path, monkeypatch):
    # what /proc does for root, whom the access check lets through: mkstemp itself fails
    def refuse(*args, **kwargs):
        raise FileNotFoundError(2, "No such file or directory")

    first = tmp_path / "first.json"
    with pytest.raises(ParqError, match="second.json: cannot write there"):
        with files.staged_files() as stage:
            stage(first, "{}")
            monkeypatch.setattr(files.tempfile, "mkstemp", refuse)
            stage(tmp_path / "second.json", "{}")
    assert list(tmp_path.iterdir()) == []


def test_os_error_is_one_line_naming_the_path():
    e = PermissionError(13, "Permission denied", "scene/color")
    assert files.os_error(e) == "scene/color: Permission denied"
    assert files.os_error(OSError(28, "No space left on device")) == "No space left on device"
