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
    WORK/matching.record.json    the stage record

A pair's key hashes the matching options (not the pair selection) and the two
images' feature keys: with new images, or another selector, only the new pairs are matched. Command line::

    python -m pipeline.matching --work WORK [--pairs auto|exhaustive|FILE|sequential:K|retrieval:K] [--ratio 0.8]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pipeline.core.atomic import write_json
from pipeline.core.errors import CacheError, InputFileError
from pipeline.core.parallel import make_executor
from pipeline.core.store import ItemStore, item_key
from pipeline.frontend import feature_stage
from pipeline.frontend.matching import FlannIndex, MatchingConfig, match_prepared, root_sift
from pipeline.frontend.pairs import choose_pairs, parse_selector
from pipeline.stage import Stage, StageRecord, fingerprint_of, read_record

logger = logging.getLogger(__name__)

__all__ = ["MatchingStage", "MatchSet", "load_matches", "main", "main_cli", "MANIFEST", "STORE"]

MANIFEST = "matches.json"
STORE = "matches"
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


def _match_chunk(args: tuple[list[tuple[str, str, str, str, str]], dict[str, Any]]) -> list[tuple[str, np.ndarray]]:
    """Worker: match a chunk of pairs ``(pair key, key a, chunk a, key b, chunk b)``."""
    tasks, cfg = args
    config = MatchingConfig(**cfg)
    out = []
    for pk, ka, ca, kb, cb in tasks:
        qa, ia = _PREPARED.get(ka, ca, config)
        qb, ib = _PREPARED.get(kb, cb, config)
        out.append((pk, match_prepared(qa, qb, ia, ib, config)))
    return out


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

    def __init__(self, work: Path, config: MatchingConfig | None = None, *, progress: bool = True) -> None:
        super().__init__(work, config)
        self.progress = progress

    def inputs(self) -> dict[str, str]:
        inp = {"features": self.upstream("features").fingerprint}
        kind, arg = parse_selector(self.config.pairs)
        if kind == "file":
            inp["pairs_file"] = fingerprint_of(Path(arg).read_bytes().decode("utf-8", "replace"))  # type: ignore[arg-type]
        return inp

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        cfg = self.config
        logger.info("matching: %s", cfg)
        fm = feature_stage.load_manifest(self.folder)
        names, fkeys = list(fm["names"]), list(fm["keys"])
        where = ItemStore(self.folder / feature_stage.STORE).load_index()
        pairs, selection = choose_pairs(cfg.pairs, names, lambda: _descriptors(self.folder, fkeys, where),
                                        cfg.exhaustive_max_images)
        logger.info("matching pairs: %s%s: %d of %d pairs (%.1f%%)", selection["selector"],
                    f" K={selection['k']}" if selection["k"] else "", selection["n_pairs"], selection["n_exhaustive"],
                    100 * selection["fraction"])
        fp = _pair_fingerprint(cfg)
        keys = [item_key(fp, fkeys[a], fkeys[b]) for a, b in pairs]
        store = ItemStore(self.folder / STORE)
        done = set() if self.overwrite else store.done(keys)
        fdir = self.folder / feature_stage.STORE
        todo = [(keys[p], fkeys[a], str(fdir / where[fkeys[a]]), fkeys[b], str(fdir / where[fkeys[b]]))
                for p, (a, b) in enumerate(pairs) if keys[p] not in done]
        chunks = [(todo[s:s + cfg.chunk_size], cfg.as_dict()) for s in range(0, len(todo), cfg.chunk_size)]
        with make_executor(min(cfg.workers, max(len(chunks), 1)), "threads") as ex, \
                tqdm(total=len(todo), desc="matching", unit="pair", disable=not self.progress) as bar:
            for res in ex.map(_match_chunk, chunks):
                store.write_chunk({pk: {"matches": m} for pk, m in res})
                bar.update(len(res))
        files = store.write_index(keys)
        counts = [len(store.get(k)["matches"]) for k in keys] if keys else []
        path = write_json(self.folder / MANIFEST, {
            "format": "rotavg-matches", "names": names, "pairs": pairs.tolist(), "keys": keys,
            "config": cfg.as_dict(), "n_pairs": len(keys), "n_computed": len(todo),
            "n_reused": len(keys) - len(todo), "selection": selection})
        logger.info("matching: %d pairs (%d matched, %d reused); median %d matches per pair", len(keys), len(todo),
                    len(keys) - len(todo), int(np.median(counts)) if counts else 0)
        return [path, *files], {"n_pairs": len(keys), "n_computed": len(todo), "pairs": selection}

    def verify(self, record: StageRecord) -> None:
        m = _load_manifest(self.folder)
        where = ItemStore(self.folder / STORE).load_index()
        if list(where) != list(m["keys"]):
            raise CacheError(f"{self.folder / MANIFEST} and its store disagree on the pairs")
        fm = feature_stage.load_manifest(self.folder)
        if list(fm["names"]) != list(m["names"]):
            raise CacheError(f"{self.folder / MANIFEST} was matched for other images than the current features")
        for chunk in sorted(set(where.values())):
            ItemStore.read_chunk(self.folder / STORE / chunk)


def _load_manifest(work: Path) -> dict:
    path = Path(work) / MANIFEST
    if not path.is_file():
        raise InputFileError(f"{path} not found: run `python -m pipeline.matching --work {work}` first")
    try:
        m = json.loads(path.read_text(encoding="utf-8"))
        pairs = np.asarray(m["pairs"], dtype=np.int64).reshape(-1, 2)
        if len(pairs) != len(m["keys"]) or (len(pairs) and (pairs.min() < 0 or pairs.max() >= len(m["names"]))):
            raise ValueError("pairs and keys disagree")
        return m
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise CacheError(f"{path} is damaged ({' '.join(str(exc).split())[:80]}); re-run pipeline.matching") from None


def load_matches(work: Path) -> MatchSet:
    """The current matches of ``work``."""
    work = Path(work)
    m = _load_manifest(work)
    store = ItemStore(work / STORE)
    store.load_index()
    matches = [store.get(k)["matches"].astype(np.int32).reshape(-1, 2) for k in m["keys"]]
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
