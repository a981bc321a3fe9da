"""Reading files the pipeline did not just compute: every failure is one error line that names the file.

A missing, truncated, damaged or foreign file gives one error that says which file
and what is wrong: never a ``BadZipFile``, ``UnicodeDecodeError``, ``KeyError`` or
``TypeError`` traceback, never numpy's advice about trusting pickled data, and
never a huge allocation from a damaged array header (each ``.npy`` header is
checked against the size of its data before an array is allocated). ``error``
picks the class: :class:`InputFileError` for a user's file, :class:`CacheError`
for a cache (which the stage that wrote it then recomputes).
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import CacheError, InputFileError, PipelineError

__all__ = ["describe", "read_text", "read_json", "read_npz", "name_list", "array_field", "MAX_TEXT_BYTES"]

MAX_TEXT_BYTES = 256 << 20  # a text file of ours (rotations, cameras, K, pairs, records) is far smaller
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # an archive, or an empty one


def describe(exc: BaseException) -> str:
    """``Type: message`` on one short line, for the parenthesis of an error naming a file."""
    msg = " ".join(str(exc).split())
    if "pickle" in msg:  # numpy's advice about trusting pickled data does not apply to a damaged file
        msg = "it holds Python objects or is not an .npz archive"
    if isinstance(exc, MemoryError):
        msg = "an array header claims more memory than the machine has"
    return f"{type(exc).__name__}: {msg[:100]}" if msg else type(exc).__name__


def _open_error(path: Path, what: str, error: type[PipelineError], exc: OSError) -> PipelineError:
    if isinstance(exc, FileNotFoundError):
        return error(f"{what} {path} does not exist")
    if isinstance(exc, IsADirectoryError):
        return error(f"{what} {path} is a folder, not a file")
    return error(f"{what} {path} cannot be read ({exc.strerror or exc})")


def read_text(path: str | os.PathLike, what: str = "file", error: type[PipelineError] = InputFileError,
              max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of ``path``; one error line for a missing, huge, unreadable or binary file."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise error(f"{what} {path} is {size >> 20} MB, far more than such a file holds; check the path")
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{what} {path} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise _open_error(path, what, error, exc) from None


def read_json(path: str | os.PathLike, what: str = "JSON file", error: type[PipelineError] = CacheError) -> Any:
    """The parsed JSON of ``path``; one error line naming it when it is missing or not JSON."""
    text = read_text(path, what, error)
    try:
        return json.loads(text)
    except ValueError as exc:
        raise error(f"{what} {path} is damaged (not JSON: {' '.join(str(exc).split())[:80]})") from None
    except RecursionError:
        raise error(f"{what} {path} is damaged (nested too deeply)") from None


def _check_header(f: Any, data_size: int) -> None:
    """Refuse an ``.npy`` member whose header claims an object dtype or more bytes than it holds."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    else:  # version 3 (UTF-8 field names): numpy reads it; its header is checked there
        return
    if dtype.hasobject:
        raise ValueError("it holds Python objects, not plain arrays")
    need = math.prod(int(n) for n in shape) * dtype.itemsize
    if need > data_size:
        raise ValueError(f"an array header claims shape {tuple(shape)} ({need} bytes) but the member holds "
                         f"{data_size} bytes")


def read_npz(path: str | os.PathLike, what: str = "file", error: type[PipelineError] = InputFileError
             ) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` file ``path``; one error line naming it when it is not a readable archive.

    Args:
        path: the file.
        what: what it should be, for messages (``"view-graph .npz file"``).
        error: the class of the error (:class:`InputFileError` or :class:`CacheError`).
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as exc:
        raise _open_error(path, what, error, exc) from None
    if magic not in _ZIP_MAGIC:
        raise error(f"{path} is not a readable {what}: it is not an .npz archive (damaged, or another kind of file)")
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    raise ValueError(f"unexpected member {info.filename!r}")
                with zf.open(info) as f:
                    _check_header(f, info.file_size)
                with zf.open(info) as f:
                    out[info.filename[: -len(".npy")]] = np.lib.format.read_array(f, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any failure (MemoryError too) means a damaged or foreign file
        raise error(f"{path} is not a readable {what} ({describe(exc)})") from None
    return out


# ------------------------------------------------ checks of parsed content (raise ValueError)
def name_list(value: Any, what: str = "names", n: int | None = None) -> list[str]:
    """``value`` as a list of unique, non-empty strings (of length ``n``), else :class:`ValueError`."""
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ValueError(f"{what} is not a list of names")
    if len(set(value)) != len(value):
        raise ValueError(f"{what} repeat a name")
    if n is not None and len(value) != n:
        raise ValueError(f"{what} has {len(value)} entries, expected {n}")
    return list(value)


def array_field(value: Any, dtype: Any, shape: tuple[int, ...], what: str, *, low: float | None = None,
                high: float | None = None) -> np.ndarray:
    """``value`` as a finite array of ``dtype`` and ``shape`` (-1: any size), within ``[low, high)``, else :class:`ValueError`."""
    a = np.asarray(value)
    if a.dtype.kind not in "biuf" or not np.isfinite(a.astype(np.float64, copy=False)).all():
        raise ValueError(f"{what} is not an array of finite numbers")
    if np.dtype(dtype).kind in "iu" and a.dtype.kind == "f" and not np.all(a == np.round(a)):
        raise ValueError(f"{what} holds non-integers")
    if a.ndim != len(shape) and not (a.size == 0 and shape[0] == -1):
        raise ValueError(f"{what} has shape {a.shape}, expected {shape}")
    a = a.reshape([(-1 if s == -1 else s) for s in shape]) if a.size == 0 else a
    if any(s != -1 and s != t for s, t in zip(shape, a.shape)):
        raise ValueError(f"{what} has shape {a.shape}, expected {shape}")
    if a.size and ((low is not None and a.min() < low) or (high is not None and a.max() >= high)):
        raise ValueError(f"{what} has values outside [{low}, {high})")
    return a.astype(dtype)
