"""Writing outputs so that a failure never leaves a partial file behind."""
from __future__ import annotations

import os
import pathlib
import tempfile

from .errors import ParqError


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
