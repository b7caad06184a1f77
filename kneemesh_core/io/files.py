"""Files that appear whole or not at all: every writer of the job folder and the service's store uses these.

A reader (a status page, a worker on another machine, a lab's client) may look at a
job folder at any moment; a file written in place can be seen half-written. Each
writer here writes a temporary file beside the target and renames it over the target
(``os.replace`` is atomic within one file system), and removes the temporary file if
the write fails.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Iterator

#: Temporary files start with this; listings of a job folder skip them.
TMP_PREFIX = ".tmp-"


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path beside ``path`` (same suffix, so writers pick the format from it);
    once the block ends without error it replaces ``path``."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    suffix = ".nii.gz" if out.name.lower().endswith(".nii.gz") else out.suffix
    fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, suffix=suffix, dir=out.parent)
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp makes it private; the output is for the lab to read
    try:
        yield tmp
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        fh.write(text)


def atomic_write_json(path: str | os.PathLike, data, indent: int = 1) -> None:
    atomic_write_text(path, json.dumps(data, indent=indent))
