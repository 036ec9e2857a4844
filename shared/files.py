"""Writing a file so that a concurrent reader sees the old or the new contents, never half."""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


def unwritable(path: str | Path) -> str | None:
    """Why ``path`` cannot be written (a missing folder, no permission), or None when it can. Checked before a
    long run whose report goes there, so the run is not lost to a typo at its end. Leaves no new file behind."""
    path = Path(path)
    existed = path.exists()
    try:
        with open(path, "a"):
            pass
    except OSError as exc:
        return f"cannot write {str(path)!r}: {exc.strerror or exc}"
    if not existed:
        path.unlink(missing_ok=True)
    return None


@contextlib.contextmanager
def exclusive(path: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on ``<path>.lock`` (a file of its own, so an atomic replace of ``path`` keeps it):
    processes sharing a file read, change and replace it in turn, and none drops another's new contents."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        yield


def write_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temp file of this call's own in the same folder
    (processes or threads sharing the folder may write at once), then rename it into place.

    A symlink is followed (its target gets the text, the link stays), and a path that is no regular file (a FIFO,
    ``/dev/stdout``, a shell's ``>(jq .)``) is written as a stream: a rename would replace the link with a file, and
    fails for ``/dev/fd/N``."""
    if os.path.exists(path) and not os.path.isfile(path):  # both follow links: /dev/fd/N leads to a pipe
        with open(path, "w") as fh:
            fh.write(text)
        return
    path = Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        os.fchmod(fd, 0o644)  # readable like any other file written here (mkstemp makes it private)
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
