"""Writing a file so that a concurrent reader sees the old or the new contents, never half."""

from __future__ import annotations

import os
import tempfile
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


def write_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temp file of this call's own in the same folder
    (processes or threads sharing the folder may write at once), then rename it into place."""
    path = Path(path)
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
