"""A structural check of a COLMAP binary model before pycolmap reads it.

pycolmap's binary readers trust every count in the file: a truncated or damaged
``images.bin`` makes them loop for minutes or allocate gigabytes. This walks the record
layout of ``cameras.bin`` and ``images.bin`` (COLMAP's documented binary format, little
endian) and bounds the leading count of ``rigs.bin``, ``frames.bin`` and ``points3D.bin``
by their sizes, so that a damaged model is refused at once with a line that names the
file. It checks the structure only; pycolmap still parses the values.

``cameras.bin``: ``u64 n``, then per camera ``i32 camera_id, i32 model_id, u64 width,
u64 height, f64 params[num_params(model_id)]``.
``images.bin``: ``u64 n``, then per image ``u32 image_id, f64 q[4], f64 t[3], u32 camera_id,
name (NUL-terminated), u64 n_points2D, n_points2D × (f64 x, f64 y, u64 point3D_id)``.
``frames.bin`` (COLMAP 4): ``u64 n``, then per frame ``u32 frame_id, u32 rig_id, f64 rig_from_world[7],
u32 n_data, n_data × (i32 sensor_type, u32 sensor_id, u64 data_id)``.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

from pipeline.core.errors import InputFileError

__all__ = ["check_binary_model", "NUM_PARAMS"]

# Parameters per COLMAP camera model id (pycolmap 4.2: CameraModelId).
NUM_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16, 12: 4, 13: 5,
              14: 3, 15: 4, 16: 6, 17: 2}
# Smallest record of the files only bounded by their count (bytes).
MIN_RECORD = {"rigs.bin": 16, "points3D.bin": 51}
MAX_NAME = 4096


def _count(path: Path, data: bytes) -> int:
    if len(data) < 8:
        raise InputFileError(f"{path}: {len(data)} bytes, too short for a COLMAP binary file (truncated?)")
    return struct.unpack_from("<Q", data)[0]


def _check_cameras(path: Path) -> None:
    data = path.read_bytes()
    n, pos = _count(path, data), 8
    if n == 0 or n * 48 > len(data) - 8:
        raise InputFileError(f"{path}: claims {n} cameras in {len(data)} bytes (truncated or damaged)")
    for k in range(n):
        if pos + 24 > len(data):
            raise InputFileError(f"{path}: ends inside camera {k + 1} of {n} (truncated)")
        model = struct.unpack_from("<i", data, pos + 4)[0]
        if model not in NUM_PARAMS:
            raise InputFileError(f"{path}: camera {k + 1} has an unknown model id {model} (damaged)")
        pos += 24 + 8 * NUM_PARAMS[model]
    if pos != len(data):
        raise InputFileError(f"{path}: {len(data) - pos:+d} bytes after its {n} cameras (truncated or damaged)")


def _check_images(path: Path) -> None:
    data = path.read_bytes()
    n, pos = _count(path, data), 8
    if n == 0 or n * 73 > len(data) - 8:
        raise InputFileError(f"{path}: claims {n} images in {len(data)} bytes (truncated or damaged)")
    for k in range(n):
        end = data.find(b"\0", pos + 64, pos + 64 + MAX_NAME)
        if pos + 64 > len(data) or end < 0:
            raise InputFileError(f"{path}: ends inside image {k + 1} of {n}, or its name is not terminated "
                                 "(truncated or damaged)")
        if end + 9 > len(data):
            raise InputFileError(f"{path}: ends inside image {k + 1} of {n} (truncated)")
        n2d = struct.unpack_from("<Q", data, end + 1)[0]
        if n2d > (len(data) - end - 9) // 24:
            raise InputFileError(f"{path}: image {k + 1} claims {n2d} keypoints beyond the file's end "
                                 "(truncated or damaged)")
        pos = end + 9 + 24 * n2d
    if pos != len(data):
        raise InputFileError(f"{path}: {len(data) - pos:+d} bytes after its {n} images (truncated or damaged)")


def _check_frames(path: Path) -> None:
    data = path.read_bytes()
    n, pos = _count(path, data), 8
    if n * 68 > len(data) - 8:
        raise InputFileError(f"{path}: claims {n} frames in {len(data)} bytes (truncated or damaged)")
    for k in range(n):
        if pos + 68 > len(data):
            raise InputFileError(f"{path}: ends inside frame {k + 1} of {n} (truncated)")
        n_data = struct.unpack_from("<I", data, pos + 64)[0]
        pos += 68 + 16 * n_data
    if pos != len(data):
        raise InputFileError(f"{path}: {len(data) - pos:+d} bytes after its {n} frames (truncated or damaged)")


def check_binary_model(folder: str | os.PathLike) -> None:
    """Refuse a COLMAP binary model whose files are truncated or damaged (one line naming the file).

    Raises:
        InputFileError: a record layout that does not fit its file.
    """
    folder = Path(folder)
    for name, check in (("cameras.bin", _check_cameras), ("images.bin", _check_images), ("frames.bin", _check_frames)):
        path = folder / name
        if name == "frames.bin" and not path.is_file():
            continue  # a COLMAP 3 model
        if not path.is_file():
            raise InputFileError(f"{path} is missing: a COLMAP binary model has cameras.bin and images.bin")
        check(path)
    for name, size in MIN_RECORD.items():
        path = folder / name
        if path.is_file():
            with path.open("rb") as f:
                head = f.read(8)
            total = path.stat().st_size
            n = _count(path, head)
            if n * size > total - 8:
                raise InputFileError(f"{path}: claims {n} records in {total} bytes (truncated or damaged)")
