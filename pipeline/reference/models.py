"""What a pycolmap reconstruction returned: its models, the summary, the result files and their reader.

Shared by the reconstruction peers (:mod:`pipeline.reference.incremental` and
:mod:`pipeline.reference.global_mapping`): every model pycolmap returns is kept in
``models-<key>/<k>/``; the largest one is the reference. Result files in the
stage's folder ``OUT``::

    OUT/model/            the largest model (COLMAP binary), readable by
                          :func:`pipeline.reference.truth.read_reference`
    OUT/rotations.txt     cam_from_world of every registered image, by name
    OUT/reference.json    summary: registered / unregistered names (with why),
                          the models and the images each one leaves out, timings,
                          configuration
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.core.atomic import atomic_dir, write_json
from pipeline.core.errors import CacheError, InputFileError
from pipeline.io.rotations import read_rotations, write_rotations
from pipeline.reference.database import verified_degree
from pipeline.reference.types import Reference

logger = logging.getLogger(__name__)

__all__ = ["SUMMARY", "ROTATIONS", "MODEL", "write_models", "load_models", "summarize_models", "write_result",
           "model_reference",
           "result_files", "read_summary", "verify_result", "load_reference"]

SUMMARY = "reference.json"
ROTATIONS = "rotations.txt"
MODEL = "model"
_TIMES = "times.json"


def write_models(models_dir: Path, produce: Callable[[Path], dict[int, Any]]) -> dict[int, Any]:
    """Run ``produce(tmp)`` (pycolmap's mapping into folder ``tmp``) and keep every model in ``models_dir/<k>/``.

    The folder is written under a tagged temporary name and renamed when complete.
    """
    with atomic_dir(models_dir) as tmp:
        t0 = time.perf_counter()
        recs = produce(tmp)
        for k, rec in recs.items():
            d = tmp / str(k)
            d.mkdir(exist_ok=True)
            rec.write(d)
        sizes = {str(p.relative_to(tmp)): p.stat().st_size for p in sorted(tmp.rglob("*")) if p.is_file()}
        write_json(tmp / _TIMES, {"map_s": time.perf_counter() - t0, "sizes": sizes})
    return recs


def load_models(pc: Any, models_dir: Path) -> tuple[dict[int, Any], float]:
    """The models kept by :func:`write_models` and the mapping time; :class:`CacheError` if damaged.

    Every file's size is checked against the one recorded before pycolmap reads
    it: pycolmap's readers can hang on a truncated file.
    """
    recs = {}
    try:
        rec = json.loads((models_dir / _TIMES).read_text(encoding="utf-8"))
        map_s, sizes = float(rec["map_s"]), dict(rec["sizes"])
        for rel, size in sizes.items():
            if (models_dir / rel).stat().st_size != int(size):
                raise ValueError(f"{rel} has {(models_dir / rel).stat().st_size} bytes, not {size}")
        for d in sorted(models_dir.iterdir(), key=lambda p: int(p.name) if p.name.isdigit() else 1 << 30):
            if d.is_dir() and d.name.isdigit():
                recs[int(d.name)] = pc.Reconstruction(d)
    except Exception as exc:  # noqa: BLE001 - any failure to read means a damaged cache
        raise CacheError(f"the models in {models_dir} are damaged ({' '.join(str(exc).split())[:80]})") from None
    return recs, map_s


def summarize_models(pc: Any, recs: dict[int, Any], db_path: Path, names: list[str], given: list[str],
                     left_out: dict[str, str], mapping: str = "incremental mapping"
                     ) -> tuple[dict[str, Any], Any, np.ndarray]:
    """The summary of what pycolmap registered, the largest model and its (n, 3, 3) rotations.

    Args:
        recs: pycolmap's models by index.
        db_path: the database they were mapped from (for why an image is unregistered).
        names: every image asked for, in order.
        given: the images handed to pycolmap (``names`` minus ``left_out``).
        left_out: ``{name: why}`` of the images not handed to pycolmap.
        mapping: the mapper's name, for the messages ("incremental mapping", ...).
    """
    models = []
    for k, rec in recs.items():
        reg = sorted(rec.images[i].name for i in rec.reg_image_ids())
        models.append({"index": k, "n_registered": len(reg), "registered": reg,
                       "left_out": sorted(set(given) - set(reg)), "n_points3D": int(rec.num_points3D())})
    models.sort(key=lambda m: (-m["n_registered"], m["index"]))
    deg, n_kp = verified_degree(pc, db_path)
    used = models[0] if models else None
    registered = used["registered"] if used else []
    R = np.zeros((len(registered), 3, 3))
    rec = recs[used["index"]] if used else None
    if rec is not None and registered:
        R = _rotations_by_name(rec, registered)
    unregistered: dict[str, str] = {}
    for nm in names:
        if nm in registered:
            continue
        other = [m for m in models[1:] if nm in m["registered"]]
        if nm in left_out:
            why = f"not given to pycolmap: it {left_out[nm]}"
        elif nm not in n_kp:
            why = "pycolmap could not read the image"
        elif n_kp[nm] == 0:
            why = "no SIFT features found"
        elif other:
            why = f"registered only in a smaller model ({other[0]['n_registered']} images, model {other[0]['index']})"
        elif deg.get(nm, 0) == 0:
            why = "no geometrically verified match with any other image"
        else:
            why = f"{deg[nm]} verified image pairs, but {mapping} could not register it"
        unregistered[nm] = why
    for nm, why in unregistered.items():
        logger.warning("pycolmap %s: %s not registered: %s", mapping, nm, why)
    for m in models[1:]:
        logger.warning("pycolmap returned another model of %d images (%s); the largest (%d images) is used; "
                       "this one leaves out %d images", m["n_registered"], ", ".join(m["registered"][:6]),
                       used["n_registered"], len(m["left_out"]))
    summary = {"images": list(names), "n_images": len(names), "n_registered": len(registered),
               "registered": registered, "unregistered": unregistered, "n_models": len(models),
               "used_model": used["index"] if used else None, "models": models}
    return summary, rec, R


def write_result(out: Path, summary: dict[str, Any], rec: Any, R: np.ndarray, header: str) -> list[Path]:
    """Write the largest model, the rotations and the summary (last); returns the files written."""
    registered = summary["registered"]
    if registered:
        with atomic_dir(out / MODEL) as tmp:
            rec.write(tmp)
        write_rotations(out / ROTATIONS, registered, R, header=header)
    else:
        shutil.rmtree(out / MODEL, ignore_errors=True)
        (out / ROTATIONS).unlink(missing_ok=True)
    write_json(out / SUMMARY, summary)
    return result_files(out)


def result_files(out: Path) -> list[Path]:
    """The result files present in ``out`` (the stage's outputs)."""
    files = [out / SUMMARY] + [p for p in [out / ROTATIONS] if p.is_file()]
    if (out / MODEL).is_dir():
        files += sorted(p for p in (out / MODEL).rglob("*") if p.is_file())
    return files


def read_summary(out: Path) -> dict[str, Any]:
    """``OUT/reference.json``; :class:`InputFileError` if absent, :class:`CacheError` if damaged."""
    path = Path(out) / SUMMARY
    if not path.is_file():
        raise InputFileError(f"{path} does not exist; run `python -m pipeline.reference` (or "
                             "`pipeline.reference.global_mapping`) first")
    try:
        s = json.loads(path.read_text(encoding="utf-8"))
        reg, unreg = list(s["registered"]), dict(s["unregistered"])
        if int(s["n_registered"]) != len(reg) or not all(isinstance(n, str) for n in [*reg, *unreg]):
            raise ValueError("n_registered and the registered names disagree")
    except (OSError, ValueError, KeyError, TypeError, OverflowError) as exc:
        raise CacheError(f"{path} is damaged ({' '.join(str(exc).split())[:80]}); re-run "
                         "`python -m pipeline.reference` (or `pipeline.reference.global_mapping`)") from None
    return s


def verify_result(out: Path) -> None:
    """:class:`CacheError` unless the summary and the rotations agree on the registered images.

    The model's files are checked by size (the stage record); pycolmap never reads
    them here, since its readers can hang on a damaged file.
    """
    s = read_summary(out)
    reg = list(s["registered"])
    if not reg:
        return
    names, R = read_rotations(out / ROTATIONS)
    if list(names) != reg or R.shape != (len(reg), 3, 3):
        raise CacheError(f"{out / ROTATIONS} holds {len(names)} cameras, not the {len(reg)} registered ones")
    if not (out / MODEL).is_dir():
        raise CacheError(f"the model {out / MODEL} is missing")


def load_reference(out: str | Path, label: str = "pycolmap") -> Reference:
    """The pycolmap reference written in ``out`` (a folder or its ``reference.json``), labelled ``label``.

    Its names are the registered images; ``unregistered`` says why each other
    image has no camera; ``info`` is the summary.
    """
    out = Path(out)
    if out.is_file():
        out = out.parent
    s = read_summary(out)
    if not s["registered"]:
        return Reference([], np.zeros((0, 3, 3)), source="pycolmap", label=label,
                         unregistered=dict(s["unregistered"]), info=s)
    names, R = read_rotations(out / ROTATIONS)
    if list(names) != list(s["registered"]):
        raise CacheError(f"{out / ROTATIONS} and {out / SUMMARY} disagree on the registered images; re-run "
                         "`python -m pipeline.reference` (or `pipeline.reference.global_mapping`)")
    return Reference(list(names), np.asarray(R), source="pycolmap", label=label,
                     unregistered=dict(s["unregistered"]), info=s)


def _rotations_by_name(rec: Any, names: list[str]) -> np.ndarray:
    """(n, 3, 3) cam_from_world rotations of the registered images ``names`` of a pycolmap model, in that order."""
    by_name = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    return np.stack([by_name[nm].cam_from_world().rotation.matrix() for nm in names])


def model_reference(out: str | Path, names: list[str], label: str = "pycolmap") -> Reference | None:
    """Of every model the peer in ``out`` returned, the one that registers most of ``names`` (a component of our
    view graph solved apart), as a reference on those of ``names`` it registers; None when none registers two.

    Its ``info`` is the peer's summary for those images: ``n_images`` and ``n_registered`` count ``names``; the
    times are those of the peer's run on every image; ``model`` is the model's index.
    """
    import pycolmap  # noqa: PLC0415

    out = Path(out)
    s = read_summary(out)
    want = set(names)
    best = max(s.get("models", []), key=lambda m: (len(want & set(m["registered"])), -m["index"]), default=None)
    folders = sorted(out.glob(f"models-*/{best['index']}")) if best is not None else []
    if best is None or len(want & set(best["registered"])) < 2 or not folders:
        return None
    rec = pycolmap.Reconstruction(str(folders[0]))
    registered = {rec.images[i].name for i in rec.reg_image_ids()}
    keep = [nm for nm in names if nm in registered]
    R = _rotations_by_name(rec, keep)
    unregistered = {nm: (s["unregistered"].get(nm) or f"registered in another of its models, not model {best['index']}")
                    for nm in names if nm not in registered}
    info = {**{k: s.get(k) for k in ("time_s", "times", "mapping", "n_models", "pycolmap")},
            "n_images": len(names), "n_registered": len(keep), "unregistered": unregistered, "model": best["index"]}
    return Reference(keep, R, source="pycolmap", label=label, unregistered=unregistered, info=info)
