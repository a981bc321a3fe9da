"""The matching stage: match the selected pairs of a WORK folder, resumable per chunk of pairs.

Pairs come from ``matching.pairs`` (:mod:`pipeline.frontend.pairs`). They are
matched in chunks of ``chunk_size`` pairs on an executor; each task reads the
descriptors it needs from the features store on disk and keeps the prepared
descriptors and FLANN indexes of recent images in a small per-process cache, so
an image's index is built about once per worker. Each finished chunk is written
at once, so an interrupted run resumes where it stopped.

WORK folder layout::

    WORK/matches.json            manifest: names, pairs (P, 2), item keys, config
    WORK/matches/chunk-*.npz     per pair: matches (m, 2) int32 keypoint indices (in a, in b)
    WORK/matches/index.json      the item keys of the current pairs
    WORK/retrieval.npz           each image's ranked neighbours by retrieval (for the loop-closure round):
                                 with retrieval, and with ``rank=True`` (sequential pairs with loop closure)
    WORK/matching.record.json    the stage record

With a loop-closure stage (:mod:`pipeline.frontend.loop_stage`) whose result is current, the
pairs are the first round's and the loop-closure pairs (``WORK/loop_closure.json``); the
record's ``base`` is the fingerprint of the first round's selection alone.

A pair's key hashes the matching options (not the pair selection) and the two
images' feature keys: with new images, or another selector, only the new pairs are matched. Command line::

    python -m pipeline.matching --work WORK [--pairs auto|exhaustive|FILE|sequential:K|retrieval:K] [--ratio 0.8]
"""

from __future__ import annotations

import argparse
import functools
import logging
import sys
import threading
import zipfile
import zlib
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from tqdm import tqdm

from pipeline.core.atomic import save_npz, write_json
from pipeline.core.errors import CacheError, ConfigError, InputFileError
from pipeline.core.readers import array_field, name_list, read_json
from pipeline.core.store import ItemStore, item_key
from pipeline.frontend import feature_stage
from pipeline.frontend.colmap_db import database_fingerprint
from pipeline.frontend.matching import FlannIndex, MatchingConfig, match_prepared, root_sift
from pipeline.frontend.pairs import choose_pairs, parse_selector, select_pairs, selection_summary
from pipeline.stage import Stage, StageRecord, fingerprint_of, read_record

logger = logging.getLogger(__name__)

__all__ = ["MatchingStage", "MatchSet", "load_matches", "load_manifest", "load_ranked", "main", "main_cli", "MANIFEST",
           "STORE", "RANKED"]

MANIFEST = "matches.json"
STORE = "matches"
RANKED = "retrieval.npz"
_CACHE_IMAGES = 48


@dataclass
class MatchSet:
    """Matches of a WORK folder (see :func:`load_matches`).

    Attributes:
        names: N image names (those of the features).
        pairs: (P, 2) image indices ``a < b``.
        matches: P arrays (m_p, 2) int32 keypoint indices (in a, in b).
        digest: the matching stage's fingerprint (downstream cache input).
    """

    names: list[str]
    pairs: np.ndarray
    matches: list[np.ndarray]
    digest: str = ""


class _Prepared:
    """Per-process cache of RootSIFT descriptors and FLANN indexes, keyed by feature item key."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.lock = threading.Lock()
        self.items: OrderedDict[tuple[str, str], tuple[np.ndarray, FlannIndex]] = OrderedDict()

    def get(self, key: str, chunk: str, config: MatchingConfig) -> tuple[np.ndarray, FlannIndex]:
        ck = (key, config.fingerprint())
        with self.lock:
            if ck in self.items:
                self.items.move_to_end(ck)
                return self.items[ck]
        q = root_sift(ItemStore.read_chunk(Path(chunk))[key]["descriptors"])
        entry = (q, FlannIndex(q, config))
        with self.lock:
            entry = self.items.setdefault(ck, entry)
            while len(self.items) > self.size:
                self.items.popitem(last=False)
        return entry


_PREPARED = _Prepared(_CACHE_IMAGES)


def _match_chunk(args: tuple[list[tuple[str, str, str, str, str]], dict[str, Any], str]) -> tuple[str, list[str]]:
    """Worker: match a chunk of pairs ``(pair key, key a, chunk a, key b, chunk b)`` and write it as one chunk of
    the matches store (folder ``args[2]``); returns the chunk's file name and its pair keys."""
    tasks, cfg, folder = args
    config = MatchingConfig(**cfg)
    out = {}
    for pk, ka, ca, kb, cb in tasks:
        qa, ia = _PREPARED.get(ka, ca, config)
        qb, ib = _PREPARED.get(kb, cb, config)
        out[pk] = {"matches": match_prepared(qa, qb, ia, ib, config)}
    return ItemStore(folder).write_chunk(out).name, list(out)


def _descriptors(work: Path, fkeys: list[str], where: dict[str, str]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Every image's descriptors (n_i, 128) uint8 and responses (n_i,), one read per feature chunk."""
    fdir = Path(work) / feature_stage.STORE
    items: dict[str, dict[str, np.ndarray]] = {}
    wanted = set(fkeys)
    for chunk in dict.fromkeys(where[k] for k in fkeys):
        items.update({k: {"descriptors": v["descriptors"], "responses": v["responses"]}
                      for k, v in ItemStore.read_chunk(fdir / chunk).items() if k in wanted})
    return [items[k]["descriptors"] for k in fkeys], [items[k]["responses"] for k in fkeys]


def _pair_fingerprint(config: MatchingConfig) -> str:
    """The options one pair's matches depend on: not which pairs were selected, so that a pair is matched
    once whichever selector (exhaustive, retrieval, a file) chose it."""
    opts = {k: v for k, v in config.result_dict().items() if k not in ("pairs", "exhaustive_max_images")}
    return fingerprint_of("matching-pair", sorted(opts.items()))


class MatchingStage(Stage[MatchingConfig]):
    """Descriptor matches of the selected image pairs of a WORK folder."""

    name = "matching"
    title = "matching"
    config_cls = MatchingConfig

    def __init__(self, work: Path, config: MatchingConfig | None = None, *, progress: bool = True,
                 loop: Any = None, rank: bool = False) -> None:
        """``loop``: a :class:`pipeline.frontend.loop_stage.LoopClosureStage`; its pairs are added when its result
        is current and adds any. ``rank``: rank each image's neighbours by retrieval for the loop-closure round
        also when the pairs are sequential."""
        super().__init__(work, config)
        self.progress = progress
        self.loop = loop
        self.rank = rank and parse_selector(self.config.pairs)[0] == "sequential"

    def _loop_record(self) -> StageRecord | None:
        """The loop-closure stage's current record when it adds pairs to this selection, else None."""
        if self.loop is None or not self.loop.applies():
            return None
        rec = self.loop.cached()
        return rec if self.loop.adds_pairs(rec) else None

    def base_fingerprint(self) -> str:
        """The fingerprint of the first round: this selection without loop-closure pairs."""
        return self.fingerprint(self.base_inputs())

    def inputs(self) -> dict[str, str]:
        inp = self.base_inputs()
        rec = self._loop_record()
        if rec is not None:
            inp["loop_closure"] = rec.fingerprint
        return inp

    def base_inputs(self) -> dict[str, str]:
        inp = {"features": self.upstream("features").fingerprint}
        kind, arg = parse_selector(self.config.pairs)
        if kind == "file":
            inp["pairs_file"] = fingerprint_of(Path(arg).read_bytes().decode("utf-8", "replace"))  # type: ignore[arg-type]
        if kind == "database" and arg is not None:
            inp["pairs_database"] = database_fingerprint(Path(arg))  # type: ignore[arg-type]
        if self.rank:
            inp["ranked"] = "retrieval"
        return inp

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        cfg = self.config
        logger.info("matching: %s", cfg)
        fm = feature_stage.load_manifest(self.folder)
        names, fkeys = list(fm["names"]), list(fm["keys"])
        fp = cfg.fingerprint()
        store = ItemStore(self.folder / STORE)
        if fm.get("database"):  # features from a COLMAP database: its verified inlier matches
            pairs, keys, n_read = self._from_database(fm, store)
            (self.folder / RANKED).unlink(missing_ok=True)
            selection = selection_summary({"spec": cfg.pairs, "selector": "database", "k": None}, len(names),
                                          len(keys))
            return self._finish(names, pairs, keys, store, n_read, selection)
        where = ItemStore(self.folder / feature_stage.STORE).load_index()
        loop = self._loop_record()
        if loop is not None:  # the loop-closure round: the first round's pairs and the loop's
            pairs, selection = self.loop.load_pairs(names)
        else:
            ranked: dict[str, np.ndarray] = {}
            pairs, selection = choose_pairs(cfg.pairs, names, lambda: _descriptors(self.folder, fkeys, where),
                                            cfg.exhaustive_max_images, ranked=ranked)
            if self.rank:  # sequential pairs, ranked for the loop-closure round
                from pipeline.frontend.retrieval import retrieve_pairs  # noqa: PLC0415 - faiss is imported on use

                descs, responses = _descriptors(self.folder, fkeys, where)
                res = retrieve_pairs(descs, None, responses=responses)
                ranked = {"neighbours": res["neighbours"], "similarities": res["similarities"]}
            if ranked:
                save_npz(self.folder / RANKED, **ranked)
                selection["ranked"] = True
            else:
                (self.folder / RANKED).unlink(missing_ok=True)
        logger.info("matching pairs: %s%s: %d of %d pairs (%.1f%%)", selection["selector"],
                    f" K={selection['k']}" if selection["k"] else "", selection["n_pairs"], selection["n_exhaustive"],
                    100 * selection["fraction"])
        fp = _pair_fingerprint(cfg)  # not the selection: another selector reuses the pairs already matched
        keys = [item_key(fp, fkeys[a], fkeys[b]) for a, b in pairs]
        fdir = (self.folder / feature_stage.STORE).resolve()  # workers may run elsewhere: absolute paths
        if not self.overwrite:
            n_kp = functools.cache(lambda a: len(ItemStore.read_chunk(fdir / where[fkeys[a]])[fkeys[a]]["keypoints"]))
            store.drop_damaged(keys, _in_range(names, pairs, n_kp), f"pairs' matches in {self.folder / STORE}")
        done = set() if self.overwrite else store.done(keys)
        todo = [(keys[p], fkeys[a], str(fdir / where[fkeys[a]]), fkeys[b], str(fdir / where[fkeys[b]]))
                for p, (a, b) in enumerate(pairs) if keys[p] not in done]
        folder = str(store.folder.resolve())
        with cfg.open_executor(-(-len(todo) // cfg.chunk_size), "threads") as ex, \
                tqdm(total=len(todo), desc="matching", unit="pair", disable=not self.progress) as bar:
            chunks = [(c, cfg.as_dict(), folder) for c in ex.chunks(todo, cfg.chunk_size)]
            for i, res in ex.each(_match_chunk, chunks):
                pair_keys = [t[0] for t in chunks[i][0]]
                store.adopt_chunk(pair_keys, None if res is None else res[0])
                bar.update(len(pair_keys))
        return self._finish(names, pairs, keys, store, len(todo), selection)

    def _from_database(self, fm: dict, store: ItemStore) -> tuple[np.ndarray, list[str], int]:
        from pipeline.frontend.database_stage import database_matches  # noqa: PLC0415

        fp, fkeys = self.config.fingerprint(), list(fm["keys"])
        kind, _ = parse_selector(self.config.pairs)
        if kind == "retrieval":
            raise ConfigError(f"[matching] pairs={self.config.pairs!r} with --database: the database's verified pairs "
                              "are used (pairs: auto or database), or a subset of them (exhaustive, sequential:K or "
                              "a pairs file)")
        selected = None if kind in ("database", "auto") else select_pairs(self.config.pairs, list(fm["names"]))
        with tqdm(desc="matches from the database", unit="pair", disable=not self.progress) as bar:
            return database_matches(fm, selected, lambda a, b: item_key(fp, fkeys[a], fkeys[b]), store,
                                    self.overwrite, bar.update)

    def _finish(self, names: list[str], pairs: np.ndarray, keys: list[str], store: ItemStore,
                n_computed: int, selection: dict[str, Any]) -> tuple[list[Path], dict[str, Any]]:
        files = store.write_index(keys)
        if selection.get("ranked") and "loop_closure" not in selection:
            files.append(self.folder / RANKED)  # the first round's: the loop-closure round reads it
        counts = [len(store.get(k)["matches"]) for k in keys] if keys else []
        path = write_json(self.folder / MANIFEST, {
            "format": "rotavg-matches", "names": names, "pairs": pairs.tolist(), "keys": keys,
            "config": self.config.as_dict(), "n_pairs": len(keys), "n_computed": n_computed,
            "n_reused": len(keys) - n_computed, "selection": selection})
        logger.info("matching: %d pairs (%d matched, %d reused); median %d matches per pair", len(keys), n_computed,
                    len(keys) - n_computed, int(np.median(counts)) if counts else 0)
        return [path, *files], {"n_pairs": len(keys), "n_computed": n_computed, "pairs": selection,
                                "base": self.base_fingerprint()}

    def verify(self, record: StageRecord) -> None:
        m = _load_manifest(self.folder)
        sel = m.get("selection") or {}
        if (sel.get("ranked") or sel.get("selector") == "retrieval") and "loop_closure" not in sel:
            load_ranked(self.folder, len(m["names"]))
        store = ItemStore(self.folder / STORE)
        if list(store.load_index()) != list(m["keys"]):
            raise CacheError(f"{self.folder / MANIFEST} and its store disagree on the pairs")
        fs = feature_stage.load_features(self.folder, descriptors=False)
        if list(fs.names) != list(m["names"]):
            raise CacheError(f"{self.folder / MANIFEST} was matched for other images than the current features")
        pairs = np.asarray(m["pairs"], np.int64).reshape(-1, 2)
        n_kp = np.array([len(k) for k in fs.keypoints], np.int64)
        store.check(m["keys"], _in_range(fs.names, pairs, n_kp.__getitem__), f"pairs' matches in {self.folder / STORE}")


def _load_manifest(work: Path) -> dict:
    path = Path(work) / MANIFEST
    if not path.is_file():
        raise InputFileError(f"{path} not found: run `python -m pipeline.matching --work {work}` first")
    m = read_json(path, "the matches manifest", CacheError)
    try:
        if not isinstance(m, dict):
            raise ValueError("not a mapping")
        n = len(name_list(m["names"], "names"))
        pairs = array_field(m["pairs"], np.int64, (-1, 2), "pairs", low=0, high=n)
        name_list(m["keys"], "keys", len(pairs))
        if np.any(pairs[:, 0] >= pairs[:, 1]):
            raise ValueError("a pair is not (a, b) with a < b")
    except (ValueError, KeyError, TypeError, OverflowError) as exc:
        raise CacheError(f"{path} is damaged ({' '.join(str(exc).split())[:80]}); re-run pipeline.matching") from None
    return m


def _in_range(names: Sequence[str], pairs: np.ndarray, n_kp: Callable[[int], int]
              ) -> Callable[[int, dict[str, np.ndarray]], None]:
    """The check of a stored pair ``q``'s matches: readable, and within its two images' ``n_kp(image)`` keypoints."""
    def check(q: int, item: dict[str, np.ndarray]) -> None:
        mm = _pair_matches(item)
        a, b = pairs[q]
        if len(mm) and (mm[:, 0].max() >= n_kp(a) or mm[:, 1].max() >= n_kp(b)):
            raise CacheError(f"the matches of {names[a]}-{names[b]} refer to keypoints the features lack")

    return check


def _pair_matches(item: Any) -> np.ndarray:
    """The (m, 2) keypoint indices of one stored pair, checked."""
    m = item["matches"]
    if not (m.ndim == 2 and m.shape[1] == 2 and m.dtype.kind in "iu" and (m.size == 0 or 0 <= m.min() <= m.max() < 2 ** 31)):
        raise CacheError(f"{item.source}: a pair's matches are damaged (shape {m.shape}, dtype {m.dtype})")
    return m.astype(np.int32)


def load_ranked(work: Path, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The retrieval's ranked neighbours (n, m) int64 and similarities (n, m) of ``work``'s n images, checked."""
    path = Path(work) / RANKED
    try:
        with np.load(path) as z:
            nb, sim = np.asarray(z["neighbours"], np.int64), np.asarray(z["similarities"], np.float64)
        if nb.ndim != 2 or nb.shape[0] != n or sim.shape != nb.shape or (nb.size and (nb.min() < 0 or nb.max() >= n)):
            raise ValueError(f"shape {nb.shape} does not fit {n} images")
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, EOFError, zlib.error) as exc:
        raise CacheError(f"{path} (the retrieval's ranked neighbours) is missing or damaged "
                         f"({' '.join(str(exc).split())[:80]}); re-run `python -m pipeline.matching --work {work}`"
                         ) from None
    return nb, sim


def load_manifest(work: Path) -> dict:
    """The matches manifest of ``work`` (names, pairs, item keys, config), checked."""
    return _load_manifest(work)


def load_matches(work: Path) -> MatchSet:
    """The current matches of ``work``, checked."""
    work = Path(work)
    m = _load_manifest(work)
    store = ItemStore(work / STORE)
    store.load_index()
    matches = [_pair_matches(store.get(k)) for k in m["keys"]]
    rec = read_record(work, MatchingStage.name)
    return MatchSet(list(m["names"]), np.asarray(m["pairs"], np.int64).reshape(-1, 2), matches,
                    rec.fingerprint if rec is not None else "")


def main(work: Path, config: MatchingConfig | None = None, pairs_path: Path | None = None, overwrite: bool = False,
         progress: bool = True) -> Path:
    """Run the stage (reusing an intact cached result); returns the manifest path."""
    config = config or MatchingConfig()
    if pairs_path is not None:
        config = config.replace(pairs=str(pairs_path))
    MatchingStage(work, config, progress=progress).run(overwrite)
    return Path(work) / MANIFEST


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import add_config_args, config_from_args, run_cli  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="python -m pipeline.matching",
                                description="Match the SIFT features of WORK (ratio test + mutual check).")
    p.add_argument("--work", type=Path, required=True, help="WORK folder written by pipeline.features")
    p.add_argument("--config", type=Path, default=None, help="YAML config; its 'matching' section is used")
    p.add_argument("--overwrite", action="store_true", help="match all pairs again")
    add_config_args(p, MatchingConfig)

    def body(a: argparse.Namespace) -> int:
        print(main(a.work, config_from_args(MatchingConfig, a, a.config), overwrite=a.overwrite,
                   progress=not a.quiet))
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
