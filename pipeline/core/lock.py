"""One run per output folder: an advisory lock on the folder itself (no lock file is left behind)."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path
from typing import Iterator

from pipeline.core.errors import PipelineError

__all__ = ["folder_lock"]


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold an exclusive lock on ``folder`` (created if needed) for the duration of the block.

    The lock lives on the folder's own file descriptor: the kernel releases it when
    this process ends, however it ends, so nothing is left to clean up.

    Raises:
        PipelineError: another run holds the folder.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise PipelineError(f"another run is writing to {folder}; wait for it to finish or choose another "
                                "--out folder") from None
        yield folder
    finally:
        os.close(fd)
