"""Writing files without ever losing a user's data.

Every output goes to a temporary name in the same folder and is renamed into
place when complete, so an interrupted run leaves only whole files; nothing
existing is replaced unless the user said --overwrite.
"""

import contextlib
import os
import tempfile
from pathlib import Path

from fem.errors import FemError


def refuse_overwrite(path, overwrite, flag="--overwrite"):
    """FemError if `path` exists (a file) or is a non-empty folder and overwrite is off."""
    path = Path(path)
    if overwrite:
        return
    if path.is_dir() and any(path.iterdir()):
        raise FemError(f"{path}: folder is not empty; use {flag} to write into it anyway")
    if path.is_file():
        raise FemError(f"{path}: file exists; use {flag} to replace it")


@contextlib.contextmanager
def atomic_open(path, mode="w"):
    """Open a temporary file beside `path`; on success it replaces `path`, on error it vanishes."""
    path = Path(path)
    if not path.parent.is_dir():
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise FemError(f"{path.parent}: cannot create folder: {e.strerror}") from None
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)   # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_path(path):
    """A temporary path beside `path` keeping its suffix (for writers that want a file name);
    call os.replace(tmp, path) when it is complete."""
    path = Path(path)
    return path.with_name(f".{path.stem}.part{path.suffix}")
