"""Atomic file writes: write to a temporary file beside the target, then rename.

An interrupted run leaves either the old file or the new one, never a torn one.
Its temporary files carry :data:`TMP_TAG` in their names, so the next run in the
same folder removes them (:func:`remove_stale_temporaries`). Outputs get the
usual permissions of a new file (0644 under the common umask 022), not the 0600
of :func:`tempfile.mkstemp`. JSON is written strict (:func:`write_json`): null where a figure is not finite.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import IO, Any, Iterator

import numpy as np

from pipeline.core.errors import OutputError

__all__ = ["atomic_path", "atomic_open", "atomic_dir", "write_json", "finite_json", "save_npz", "save_npz_uncompressed",
           "save_figure", "remove_stale_temporaries", "check_writable", "TMP_TAG"]

TMP_TAG = ".rotavg-tmp-"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _publish(tmp: Path, path: Path, mode: int = 0o666) -> None:
    os.chmod(tmp, mode & ~_umask())
    os.replace(tmp, path)


def _cannot_write(path: Path, exc: OSError) -> OutputError:
    """The error of an output whose temporary cannot be made beside it: it names the output, not the temporary."""
    return OutputError(f"cannot write {path} ({exc.strerror or exc}); choose a writable location")


def check_writable(folder: str | os.PathLike, what: str = "") -> None:
    """Create ``folder`` if needed and a file in it (removed at once): before the work that writes there.

    Raises:
        OutputError: naming ``folder`` (and ``what`` writes there), where either cannot be done.
    """
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".probe{TMP_TAG}")
    except OSError as exc:
        raise OutputError(f"cannot write to {folder} ({exc.strerror or exc}){': ' + what if what else ''}; choose a "
                          "writable folder") from None
    os.close(fd)
    os.unlink(tmp)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto ``path`` on success.

    Args:
        path: final destination.
        suffix: suffix of the temporary file (default: that of ``path``), for
            writers such as ``np.savez`` that append their own extension.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}{TMP_TAG}",
                                   suffix=suffix if suffix is not None else path.suffix)
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        _publish(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; it replaces ``path`` (and anything there) on success."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}{TMP_TAG}"))
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())
        if path.exists():
            old = path.with_name(f".{path.name}{TMP_TAG}old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w") -> Iterator[IO[Any]]:
    """Open a temporary file for writing; it replaces ``path`` when the block exits cleanly."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())


#: Values that are JSON as they are (``bool`` is a subclass of ``int``, but ``type`` tells them apart).
_PLAIN = (str, int, bool, type(None))


def finite_json(obj: Any) -> Any:
    """``obj`` as plain JSON values, with every NaN or infinite float as None: what :func:`write_json` writes is
    strict JSON (NaN and Infinity are not JSON, and most readers refuse them); null means "not defined" (an estimate
    made from no pair, an undefined bound). numpy arrays become lists and numpy scalars Python numbers.

    The exact built-in types are tested first (``type(...) is``): a view graph's summary of 300k pairs converts in
    1.1 s instead of 2.0 s with ``isinstance`` alone.
    """
    t = type(obj)
    if t is float:
        return obj if math.isfinite(obj) else None
    if t in _PLAIN:
        return obj
    if t is dict or isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if t is list or t is tuple or isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_json(obj.tolist())
    if isinstance(obj, np.generic):
        return finite_json(obj.item())
    if isinstance(obj, float):  # another subclass of float
        return float(obj) if math.isfinite(obj) else None
    return obj


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented strict JSON atomically: numpy scalars and arrays are converted and every NaN or
    infinite float is written as null (:func:`finite_json`); paths are written as strings. Anything else that is
    not JSON raises, and so would a NaN or infinity left over: the encoder never writes ``NaN`` or ``Infinity``."""

    def default(o: Any) -> Any:
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"{type(o).__name__} is not JSON serializable")

    with atomic_open(path) as f:
        json.dump(finite_json(obj), f, indent=2, default=default, allow_nan=False)
        f.write("\n")
    return Path(path)


def save_npz(path: str | os.PathLike, **arrays: Any) -> Path:
    """A compressed ``.npz`` (what ``np.load`` reads) written atomically to exactly ``path``.

    zlib's fastest level: float arrays barely compress at any level, and numpy's default (6) took a third
    of a second on a 16-image view graph's correspondences, serial work in the process that assembles them.
    """
    with atomic_path(path, suffix=".npz") as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            for name, value in arrays.items():
                with zf.open(name + ".npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)
    return Path(path)


def save_npz_uncompressed(path: str | os.PathLike, **arrays: Any) -> Path:
    """``np.savez`` written atomically to exactly ``path``: for caches written often, where zlib costs more than disk."""
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, **arrays)
    return Path(path)


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 110, close: bool = True) -> Path:
    """Write a matplotlib figure as PNG atomically; close it unless ``close=False``."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    if close:
        import matplotlib.pyplot as plt  # noqa: PLC0415 - only callers that plot pay for the import

        plt.close(fig)
    return Path(path)


def remove_stale_temporaries(folder: str | os.PathLike) -> int:
    """Remove the temporary files and folders an interrupted run left under ``folder``.

    Only names carrying :data:`TMP_TAG` are touched. Call it while holding the
    folder's lock (:func:`pipeline.core.lock.folder_lock`), never while another
    writer works in the same folder. Returns the number of entries removed.
    """
    folder = Path(folder)
    n = 0
    if not folder.is_dir():
        return 0
    for root, dirs, files in os.walk(folder):
        for d in [d for d in dirs if TMP_TAG in d]:
            shutil.rmtree(Path(root) / d, ignore_errors=True)
            dirs.remove(d)
            n += 1
        for f in files:
            if TMP_TAG in f:
                with contextlib.suppress(FileNotFoundError):
                    (Path(root) / f).unlink()
                n += 1
    return n
