"""Seeded, deterministic damage to files: what the fuzzer and the bad-input tests feed every reader.

A damaged copy of a good file is made at one of four levels, chosen by the file's
kind, so that a reader meets both broken containers and well-formed files with
nonsense inside:

- **bytes** (any file): flip bytes, truncate, insert random bytes, zero a span,
  cut to nothing, append garbage;
- **text** (text files): delete, duplicate or swap lines; replace a numeric token
  by ``nan``, ``inf``, ``-1``, ``0``, ``1e308`` or a huge integer; drop or add a
  field; put non-UTF-8 bytes or an unbalanced quote in a line;
- **JSON** (``.json``): replace a leaf by a number, string, null, list or nesting;
  delete a key; drop or duplicate list elements;
- **arrays** (``.npz``, ``.mat``): change one array's shape, dtype or values
  (NaN, inf, huge, negative), make it 0-d, delete it, add a stray one.

Every function takes a :class:`numpy.random.Generator`; the same seed gives the
same damage. :func:`damaged_copies` yields ``n`` damaged copies of a file or of a
folder (one file of it damaged each time) with a description of each.
"""

from __future__ import annotations

import io
import json
import re
import shutil
from pathlib import Path
from typing import Any, Iterator

import numpy as np

__all__ = ["mutate_bytes", "mutate_text", "mutate_json", "mutate_arrays", "damage_file", "damaged_copies",
           "NUMBER_SWAPS"]

#: What a numeric token is replaced with.
NUMBER_SWAPS = ("nan", "inf", "-inf", "-1", "0", "1e308", "-1e308", "99999999999999999999", "4294967297", "1e-320",
                "abc", "")
_NUMBER = re.compile(r"(?<![\w.])[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?(?![\w.])")
_TEXT_SUFFIXES = {".txt", ".yaml", ".yml", ".json", ".camera", ".csv"}


def mutate_bytes(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """One byte-level damage of ``data`` and its description."""
    b = bytearray(data)
    n = len(b)
    kind = rng.choice(["flip", "truncate", "insert", "zero", "empty", "append", "flip_header"])
    if n == 0 or kind == "append":
        extra = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
        return bytes(b) + extra, f"append {len(extra)} random bytes"
    if kind == "empty":
        return b"", "cut to 0 bytes"
    if kind == "truncate":
        k = int(rng.integers(0, n))
        return bytes(b[:k]), f"truncate to {k} of {n} bytes"
    if kind == "insert":
        k = int(rng.integers(0, n))
        extra = rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8).tobytes()
        return bytes(b[:k]) + extra + bytes(b[k:]), f"insert {len(extra)} bytes at {k}"
    if kind == "zero":
        k = int(rng.integers(0, n))
        m = int(rng.integers(1, max(2, n // 4)))
        b[k:k + m] = bytes(len(b[k:k + m]))
        return bytes(b), f"zero {m} bytes at {k}"
    span = min(n, 64) if kind == "flip_header" else n
    ks = rng.integers(0, span, int(rng.integers(1, 5)))
    for k in ks:
        b[int(k)] ^= int(rng.integers(1, 256))
    return bytes(b), f"flip bytes at {sorted(int(k) for k in ks)}"


def mutate_text(text: str, rng: np.random.Generator) -> tuple[bytes, str]:
    """One text-level damage of ``text`` (returned as bytes: some damage is not UTF-8)."""
    lines = text.split("\n")
    kind = rng.choice(["number", "number", "number", "delete_line", "dup_line", "swap_lines", "drop_field",
                       "add_field", "non_utf8", "quote", "blank_name"])
    body = [k for k, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")] or [0]
    k = int(rng.choice(body))
    if kind == "number":
        spans = [m.span() for m in _NUMBER.finditer(text)]
        if spans:
            s, e = spans[int(rng.integers(0, len(spans)))]
            new = str(rng.choice(NUMBER_SWAPS))
            return (text[:s] + new + text[e:]).encode(), f"number {text[s:e]!r} -> {new!r} at char {s}"
        kind = "delete_line"
    if kind == "delete_line":
        del lines[k]
        return "\n".join(lines).encode(), f"delete line {k + 1}"
    if kind == "dup_line":
        lines.insert(k, lines[k])
        return "\n".join(lines).encode(), f"duplicate line {k + 1}"
    if kind == "swap_lines":
        j = int(rng.choice(body))
        lines[k], lines[j] = lines[j], lines[k]
        return "\n".join(lines).encode(), f"swap lines {k + 1} and {j + 1}"
    fields = lines[k].split(" ")
    if kind == "drop_field" and len(fields) > 1:
        del fields[int(rng.integers(0, len(fields)))]
        lines[k] = " ".join(fields)
        return "\n".join(lines).encode(), f"drop a field of line {k + 1}"
    if kind == "add_field":
        fields.insert(int(rng.integers(0, len(fields) + 1)), str(rng.choice(["1", "x", "nan", "0.5"])))
        lines[k] = " ".join(fields)
        return "\n".join(lines).encode(), f"add a field to line {k + 1}"
    if kind == "quote":
        lines[k] = '"' + lines[k]
        return "\n".join(lines).encode(), f"unbalanced quote in line {k + 1}"
    if kind == "blank_name":
        lines[k] = '"" ' + " ".join(fields[1:])
        return "\n".join(lines).encode(), f"empty name in line {k + 1}"
    raw = bytearray("\n".join(lines).encode())
    pos = int(rng.integers(0, len(raw) + 1))
    raw[pos:pos] = b"\xff\xfe\xc3"
    return bytes(raw), f"non-UTF-8 bytes at {pos}"


def _leaves(obj: Any, path: tuple = ()) -> list[tuple]:
    out = [path]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _leaves(v, path + (k,))
    elif isinstance(obj, list):
        for k, v in enumerate(obj[:50]):
            out += _leaves(v, path + (k,))
    return out


def _get(obj: Any, path: tuple) -> Any:
    for p in path:
        obj = obj[p]
    return obj


def mutate_json(obj: Any, rng: np.random.Generator) -> tuple[Any, str]:
    """One structural damage of parsed JSON (a deep copy is changed)."""
    obj = json.loads(json.dumps(obj))
    paths = _leaves(obj)
    path = paths[int(rng.integers(0, len(paths)))]
    kind = rng.choice(["replace", "replace", "delete", "drop_item", "dup_item"])
    replacements: list[Any] = [float("nan"), float("inf"), -1, 0, 1e308, 10 ** 20, "x", None, [], {}, [1, 2],
                               True, [[0, 0, 0]] * 3]
    if not path:
        new = replacements[int(rng.integers(0, len(replacements)))]
        return new, f"whole document -> {new!r}"
    parent, key = _get(obj, path[:-1]), path[-1]
    if kind == "delete" and isinstance(parent, dict):
        del parent[key]
        return obj, f"delete {'/'.join(map(str, path))}"
    if kind in ("drop_item", "dup_item") and isinstance(parent, list):
        if kind == "drop_item":
            del parent[key]
        else:
            parent.insert(key, parent[key])
        return obj, f"{kind} {'/'.join(map(str, path))}"
    new = replacements[int(rng.integers(0, len(replacements)))]
    parent[key] = new
    return obj, f"{'/'.join(map(str, path))} -> {new!r}"


def mutate_arrays(arrays: dict[str, np.ndarray], rng: np.random.Generator) -> tuple[dict[str, np.ndarray], str]:
    """One damage of a mapping of arrays (shape, dtype, values, a missing or a stray array)."""
    out = {k: np.array(v) for k, v in arrays.items()}
    if not out:
        return {"stray": np.zeros(3)}, "add a stray array"
    key = sorted(out)[int(rng.integers(0, len(out)))]
    a = out[key]
    kind = rng.choice(["nan", "inf", "huge", "negative", "zero_d", "reshape", "drop_row", "dtype_str", "dtype_float",
                       "delete", "stray", "empty"])
    if kind in ("nan", "inf", "huge", "negative") and a.size and a.dtype.kind in "biuf":
        b = a.astype(np.float64) if kind in ("nan", "inf") else a.copy()
        if kind == "negative" and b.dtype.kind in "ub":
            b = b.astype(np.int64)
        idx = tuple(int(rng.integers(0, n)) for n in b.shape)
        b[idx] = {"nan": np.nan, "inf": np.inf, "huge": np.iinfo(b.dtype).max if b.dtype.kind in "iu" else
                  (True if b.dtype.kind == "b" else 1e308), "negative": -1}[kind]
        out[key] = b
        return out, f"{key}[{idx}] -> {kind}"
    if kind == "zero_d" or (a.size == 0 and kind in ("nan", "inf", "huge", "negative")):
        out[key] = np.array(a.ravel()[0] if a.size else 0)
        return out, f"{key} made 0-d"
    if kind == "reshape" and a.size:
        out[key] = a.reshape(-1)
        return out, f"{key} flattened to {out[key].shape}"
    if kind == "drop_row" and a.ndim and len(a):
        out[key] = a[:-1]
        return out, f"{key} lost its last row"
    if kind == "dtype_str":
        out[key] = a.astype(str)
        return out, f"{key} as strings"
    if kind == "dtype_float" and a.dtype.kind in "biu":
        out[key] = a.astype(np.float64) + 0.5
        return out, f"{key} as non-integer floats"
    if kind == "delete":
        del out[key]
        return out, f"delete {key}"
    if kind == "empty":
        out[key] = a[:0] if a.ndim else np.zeros(0)
        return out, f"{key} emptied"
    out["stray"] = rng.normal(size=(2, 2))
    return out, "add a stray array"


def _save_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    if path.suffix.lower() == ".mat":
        import scipy.io as sio  # noqa: PLC0415

        sio.savemat(path, {k: v for k, v in arrays.items() if v.dtype.kind != "U" or v.size}, do_compression=True)
    else:
        buf = io.BytesIO()
        np.savez(buf, **arrays)  # uncompressed: cheaper, and readers must take both
        path.write_bytes(buf.getvalue())


def _load_arrays(path: Path) -> dict[str, np.ndarray] | None:
    try:
        if path.suffix.lower() == ".mat":
            import scipy.io as sio  # noqa: PLC0415

            return {k: v for k, v in sio.loadmat(path).items() if not k.startswith("__")}
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception:  # noqa: BLE001 - not an array file: damage its bytes only
        return None


def damage_file(path: Path, rng: np.random.Generator) -> str:
    """Damage the file ``path`` in place at a level chosen for its kind; returns what was done."""
    data = path.read_bytes()
    suffix = path.suffix.lower()
    level = rng.random()
    if suffix in (".npz", ".mat") and level < 0.6:
        arrays = _load_arrays(path)
        if arrays is not None:
            arrays, what = mutate_arrays(arrays, rng)
            _save_arrays(path, arrays)
            return f"arrays: {what}"
    if suffix == ".json" and level < 0.4:
        try:
            obj = json.loads(data.decode("utf-8"))
        except ValueError:
            obj = None
        if obj is not None:
            obj, what = mutate_json(obj, rng)
            path.write_text(json.dumps(obj, indent=1))
            return f"json: {what}"
    if (suffix in _TEXT_SUFFIXES or suffix == "") and level < 0.75:
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            text = None
        if text is not None:
            raw, what = mutate_text(text, rng)
            path.write_bytes(raw)
            return f"text: {what}"
    raw, what = mutate_bytes(data, rng)
    path.write_bytes(raw)
    return f"bytes: {what}"


def damaged_copies(src: Path, work: Path, n: int, seed: int, files: list[str] | None = None
                   ) -> Iterator[tuple[int, Path, str]]:
    """``n`` damaged copies of the file or folder ``src``, one at a time, in ``work``.

    Args:
        src: a good file, or a folder of good files (one of them is damaged in each copy).
        work: a scratch folder; each copy replaces the previous one there.
        n: number of copies.
        seed: the seed of every choice.
        files: for a folder, the names of the files that may be damaged (default: all).

    Yields:
        ``(k, path of the copy, description)``.
    """
    rng = np.random.default_rng(seed)
    src = Path(src)
    work = Path(work)
    for k in range(n):
        dst = work / src.name
        if dst.is_dir():
            shutil.rmtree(dst)
        elif dst.exists():
            dst.unlink()
        work.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, dst)
            names = sorted(files or [p.relative_to(src).as_posix() for p in src.rglob("*") if p.is_file()])
            target = dst / names[int(rng.integers(0, len(names)))]
        else:
            shutil.copyfile(src, dst)
            target = dst
        what = damage_file(target, rng)
        yield k, dst, f"{target.relative_to(work)}: {what}"
