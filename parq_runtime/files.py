"""Reading JSON inputs with one-line errors, and writing outputs (files and folders) so that
a failure never leaves a partial one behind."""
from __future__ import annotations

import contextlib
import json
import os
import pathlib
import shutil
import sys
import tempfile

from .errors import ParqError


def read_json(path):
    """The parsed contents of a JSON file; ParqError naming the file when it is missing or
    not JSON."""
    try:
        return json.loads(pathlib.Path(path).read_text())
    except FileNotFoundError:
        raise ParqError(f"{path}: not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ParqError(f"{path}: not readable JSON ({e})") from None


def os_error(e: OSError) -> str:
    """One line for an OSError: the path it names and the system's reason."""
    where = f"{e.filename}: " if e.filename is not None else ""
    return f"{where}{e.strerror or e}"


def write_stdout(text: str) -> None:
    """``text`` and a newline on stdout.  A reader that stops early (``| head``) closes the
    pipe: the output then ends quietly instead of with a traceback."""
    try:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
    except BrokenPipeError:
        # Python would hit the closed pipe again when it flushes stdout at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def check_writable(path) -> pathlib.Path:
    """Fail early, before any work, if ``path`` cannot be created: it is a folder, its folder
    is missing or not writable, or a trial file beside it (created and removed, as the
    outputs' temporary files are) cannot be made there: access() says yes to root anywhere,
    /proc included, and a name can be too long."""
    path = pathlib.Path(path)
    parent = path.absolute().parent
    try:
        if path.is_dir():
            raise ParqError(f"{path}: is a folder, expected a file name")
        if not parent.is_dir():
            raise ParqError(f"{parent}: folder does not exist")
        if not os.access(parent, os.W_OK):
            raise ParqError(f"{parent}: not writable")
        fd, trial = tempfile.mkstemp(prefix=f".{path.name}.", dir=parent)
        os.close(fd)
        os.unlink(trial)
    except OSError as e:
        raise ParqError(f"{path}: cannot write there ({e.strerror or e})") from None
    return path


def atomic_write(path, data) -> None:
    """Write bytes or text to a temporary file beside ``path``, then rename it into place."""
    with staged_files() as stage:
        stage(path, data)


@contextlib.contextmanager
def staged_files():
    """``with staged_files() as stage: stage(path, data); ...`` writes each file to a
    temporary file beside its path (bytes or text); when the block ends without error all of
    them are renamed into place, and on any error all are removed: the outputs of one command
    appear together or not at all.  An OSError becomes ParqError naming the path."""
    staged = []

    def stage(path, data) -> None:
        path = check_writable(path)
        staged.append((_write_beside(path, data), path))

    try:
        yield stage
        for tmp, path in staged:
            try:
                os.replace(tmp, path)
            except OSError as e:
                raise ParqError(f"{path}: could not write ({e.strerror or e})") from None
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)


def _write_beside(path: pathlib.Path, data) -> pathlib.Path:
    """``data`` in a new temporary file in ``path``'s folder; returns its path."""
    mode = "wb" if isinstance(data, (bytes, bytearray)) else "w"
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.absolute().parent)
    except OSError as e:
        raise ParqError(f"{path}: cannot write there ({e.strerror or e})") from None
    tmp = pathlib.Path(tmp)
    try:
        with os.fdopen(fd, mode) as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~umask())
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise ParqError(f"{path}: could not write ({e.strerror or e})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


@contextlib.contextmanager
def atomic_folder(folder, what: str):
    """``with atomic_folder(folder, "the scene") as tmp:`` yields an empty temporary folder
    beside ``folder`` to fill.  When the block ends without error it becomes ``folder``: an
    existing folder is moved aside first and put back if the rename fails, so ``folder`` is
    never missing or half-written.  On any error the temporary folder is removed, and an
    OSError becomes ParqError("FOLDER: could not write WHAT (...)")."""
    folder = pathlib.Path(folder)
    parent = folder.absolute().parent
    try:
        tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp",
                                            dir=parent))
    except OSError as e:
        raise ParqError(f"{parent}: cannot write there ({e.strerror or e})") from None
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~umask())     # mkdtemp makes it private; outputs are not
        _swap_into_place(tmp, folder)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise ParqError(f"{folder}: could not write {what} ({e.strerror or e})") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _swap_into_place(tmp: pathlib.Path, folder: pathlib.Path) -> None:
    if not folder.exists():
        os.replace(tmp, folder)
        return
    old = pathlib.Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".old",
                                        dir=folder.absolute().parent))
    os.replace(folder, old / "previous")
    try:
        os.replace(tmp, folder)
    except OSError:
        os.replace(old / "previous", folder)
        old.rmdir()
        raise
    shutil.rmtree(old, ignore_errors=True)


def umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
