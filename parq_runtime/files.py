"""Reading JSON inputs with one-line errors, and writing outputs so that a failure never
leaves a partial file behind."""
from __future__ import annotations

import json
import os
import pathlib
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


def check_writable(path) -> pathlib.Path:
    """Fail early, before any work, if ``path`` cannot be created."""
    path = pathlib.Path(path)
    parent = path.absolute().parent
    if path.is_dir():
        raise ParqError(f"{path}: is a folder, expected a file name")
    if not parent.is_dir():
        raise ParqError(f"{parent}: folder does not exist")
    if not os.access(parent, os.W_OK):
        raise ParqError(f"{parent}: not writable")
    return path


def atomic_write(path, data) -> None:
    """Write bytes or text to a temporary file beside ``path``, then rename it into place."""
    path = check_writable(path)
    mode = "wb" if isinstance(data, (bytes, bytearray)) else "w"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.absolute().parent)
    try:
        with os.fdopen(fd, mode) as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~umask())
        os.replace(tmp, path)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise


def umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
