"""The whole pipeline on the default scene, fountain-P11, temple, and rendered scenes, against both pycolmap peers.

    python benchmarks/end_to_end.py [--quick] [--only default,fountain,temple,rendered] [--keep DIR]

Each case runs ``run.py``'s ``main()`` in a fresh output folder (nothing reused) with
run.py's default methods (no ``--methods``: IRLS-ℓ½, IRLS-H-ℓ½, SDP-cSO(3) and colmap-ra
on these graphs), the refinement of the recommended method (the row ``<start>+refine``)
and both peers, pycolmap incremental and pycolmap global (GLOMAP), in the same process
right after ours (as near the same machine load as a shared machine allows). That run is
the timed one. Reported per case, from its ``metrics.json``:

- every method row (each averaging method, ``colmap-ra``, ``<start>+refine``, a second
  opinion where one ran) and both peers against the truth (median, mean, RMS, max error
  in degrees; cameras evaluated), each method's median against each peer, and, where a
  peer leaves images out, each method on that peer's registered images only (aligned on
  them, ``on_<peer>_images``: the like-for-like comparison);
- the peers' registered counts and times, each the peer's own extraction + matching +
  mapping (the two peers share one database, built once by the incremental peer; GLOMAP
  is charged the same extraction and matching seconds, from the database's timings);
- our path's wall time two ways, from run.py's stage times: (a) to rotations, features →
  averaging (features, matching, cameras, two-view, two-view BA, loop closure, view graph,
  averaging of every default method), and (b) ``metrics.json``'s ``our_path_s``, which is
  (a) plus the refinement; each over each peer's time (four ratios);
- images our view graph leaves out and images each peer does not register, with why.

"Anisotropy pays": SDP-cSO(3) (with our H) vs SDP-O(3)-ISO, and IRLS-H-ℓ½ vs IRLS-ℓ½,
side by side. SDP-O(3)-ISO is not a default method: after the timed run, ``run.main`` runs
again in the same folder with the default methods plus ``sdp-o3-iso`` (every other stage
reused), and only that row is taken from it (``extra_methods``), so the timed run is
exactly a default run; the folder's ``metrics.json`` is then the second run's, and the timed
run's is kept beside it as ``metrics.timed.json`` (``--keep``). On temple, where the view
graph holds pairs the front end flagged degenerate (small baseline, or planar), the methods
are also run without them (a row of its own; none when no pair is flagged).

Results: ``benchmarks/results/end_to_end.json`` (atomic, ``{"rows", "command", "machine"}``;
with ``--only``, the other cases' rows are kept from it) and a table. Data: ``../shared/data``,
read in place (Strecha fountain-P11: Strecha et al.
CVPR 2008, via openMVG's SfM_quality_evaluation; Middlebury templeSparseRing: Seitz et al.
CVPR 2006).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("MPLBACKEND", "Agg")

import argparse  # noqa: E402
import atexit  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from _common import save_results  # noqa: E402  (benchmarks/, the script's folder)
from pipeline.evaluation.assemble import OUR_PATH  # noqa: E402
from pipeline.evaluation.compare import subset_prefix  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "benchmarks" / "results" / "end_to_end.json"
#: what the second, untimed run adds to the default methods (the isotropic SDP of the anisotropy comparison)
EXTRA_METHODS = ["sdp-o3-iso"]
PEERS = ("pycolmap", "glomap")  # metrics.json's peer keys: pycolmap incremental, pycolmap global (GLOMAP)
PEER_TITLE = {"pycolmap": "pycolmap-incr", "glomap": "glomap"}
REFINE_SUFFIX = "+refine"
SUMMARY = ("n_cameras", "n_evaluated", "median_deg", "mean_deg", "rms_deg", "max_deg")


def method_row(s: dict, peers: list[str]) -> dict:
    """One method's figures: against the truth, against each peer, on each peer's images, its time and certificate."""
    refs = s.get("references") or {}
    truth = refs.get("truth") or {}
    row = {k: truth.get(k) for k in (*SUMMARY, "frobenius", "mahalanobis")}
    row["n_cameras"] = s.get("n_cameras", row["n_cameras"])
    row["time_s"] = s.get("time_s")
    for k in ("certified", "rank", "gap", "status", "start", "n_refined", "sigma_median_deg"):
        if k in s:
            row[k] = s[k]
    verdict = (s.get("certificate") or {}).get("verdict") if isinstance(s.get("certificate"), dict) else None
    if verdict:
        row["certificate_verdict"] = verdict
    for p in peers:
        if p in refs:
            row[f"vs_{p}_median_deg"] = refs[p].get("median_deg")
        for ref_name, sub in refs.items():
            if ref_name.startswith(subset_prefix(p)):  # run.py's like-for-like reference on the peer's images
                row[f"on_{p}_images"] = {k: sub.get(k) for k in SUMMARY}
    return row


def peer_row(p: dict) -> dict:
    """One peer's figures: against the truth, registered counts, time (extraction + matching + mapping)."""
    row = {k: p.get(k) for k in ("mapping", "n_images", "n_registered", "n_models", *SUMMARY, "time_s", "times",
                                 "unregistered")}
    row["vs_peers_median_deg"] = {q: v.get("median_deg") for q, v in (p.get("references") or {}).items()}
    return row


def case_row(name: str, m: dict, wall_s: float) -> dict:
    """The figures of one run's metrics.json that the benchmark reports."""
    stages = m["stages"]
    peers_m = m.get("peers") or ({"pycolmap": m["pycolmap"]} if m.get("pycolmap") else {})
    peers = [p for p in PEERS if peers_m.get(p)] + [p for p in peers_m if p not in PEERS and peers_m[p]]
    with_refine = m.get("our_path_s")
    # (a) features → averaging: run.py's OUR_PATH without the refinement (checked: the two sums agree)
    to_rotations = sum(stages.get(k, 0.0) for k in OUR_PATH if k != "refine")
    row: dict = {"case": name, "wall_s": wall_s, "total_s": m.get("total_s"), "stages": stages,
                 "stages_reused": m.get("stages_reused"),
                 "our_path_rotations_s": to_rotations, "our_path_s": with_refine,
                 "our_path_stages": list(OUR_PATH),
                 "n_images": m["input"]["n_images"], "n_cameras_graph": m["input"]["n_cameras_graph"],
                 "n_edges": m["input"]["n_edges"], "left_out_by_view_graph": m["input"].get("left_out_why")
                 or m["input"]["left_out"], "components": m.get("components") or [],
                 "n_flagged": (m.get("evidence") or {}).get("n_flagged"),
                 "methods": {label: method_row(s, peers) for label, s in m["methods"].items()},
                 "peers": {p: peer_row(peers_m[p]) for p in peers}, "edges": m.get("edges", {}),
                 "notes": m.get("notes", [])}
    if with_refine is not None and abs(with_refine - to_rotations - stages.get("refine", 0.0)) > 1e-6:
        raise RuntimeError(f"{name}: our_path_s {with_refine} is not the stages {OUR_PATH}' sum "
                           f"{to_rotations + stages.get('refine', 0.0)}: run.py's our_path_s changed meaning")
    ratios = {}
    for p in peers:
        t = row["peers"][p].get("time_s")
        if t:
            ratios[f"rotations_over_{p}"] = to_rotations / t
            if with_refine is not None:
                ratios[f"with_refine_over_{p}"] = with_refine / t
    row["time_ratios"] = ratios
    return row


def default_labels(m: dict) -> list[str]:
    """The averaging methods of a run (its rows without the refinement's), as ``--methods`` tokens."""
    return [label for label, s in m["methods"].items()
            if not label.endswith(REFINE_SUFFIX) and s.get("method") != "refine"]


def run_case(run, name: str, images: Path | None, gt: Path | None, K: Path | None, work_root: Path,
             config: Path | None = None) -> dict:
    """The timed default run in a fresh folder, then the extra methods' run in the same folder (stages reused)."""
    out = work_root / name
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    p = run.main(images, out, config=config, gt=gt, K=K, quiet=True)
    wall = time.perf_counter() - t0
    m = json.loads(Path(p).read_text())
    row = case_row(name, m, wall)
    print(f"  {name}: {wall:.1f} s", flush=True)
    shutil.copyfile(p, out / "metrics.timed.json")  # the second run writes metrics.json again
    if EXTRA_METHODS:
        # images=None renders the default scene again into OUT/scene; the rendering is deterministic
        t0 = time.perf_counter()
        p2 = run.main(images, out, config=config, methods=default_labels(m) + EXTRA_METHODS, gt=gt, K=K,
                      quiet=True)
        m2 = json.loads(Path(p2).read_text())
        peers = list(row["peers"])
        row["extra_methods"] = {label: method_row(m2["methods"][label], peers) for label in m2["methods"]
                                if label not in m["methods"]}
        # the rows both runs have must agree (the second run reused them): a check that nothing was recomputed
        drift = {label: (row["methods"][label]["median_deg"], method_row(s, peers)["median_deg"])
                 for label, s in m2["methods"].items() if label in row["methods"]
                 and row["methods"][label]["median_deg"] != method_row(s, peers)["median_deg"]}
        if drift:
            row["extra_run_drift"] = drift
            print(f"  {name}: the extra-methods run changed rows of the timed run: {drift}", flush=True)
        row["extra_run_s"] = time.perf_counter() - t0
        row["extra_run_stages_reused"] = m2.get("stages_reused")
        print(f"  {name} (+{', '.join(EXTRA_METHODS)}): {row['extra_run_s']:.1f} s", flush=True)
    return row


def without_degenerate(name: str, out: Path, gt: Path, tokens: list[str]) -> dict | None:
    """Re-average a run's view graph without the edges the front end flagged degenerate.

    On temple, images 0001 and 0011 have identical true poses: their pair has zero parallax,
    an accurate rotation and an H orders of magnitude above the others. This row shows what
    the methods (``tokens``, with run.py's options from the default config) do without it.
    """
    import numpy as np

    from pipeline.average import average
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.compare import match_reference
    from pipeline.evaluation.metrics import summarize
    from pipeline.plan import load_configs
    from pipeline.reference.truth import read_reference

    vg = ViewGraph.load(out / "viewgraph.npz")
    flag = np.asarray(vg.stats.get("degenerate", np.zeros(vg.n_edges, bool)), bool)
    if not flag.any():
        return None
    keep = ~flag
    sub = ViewGraph(vg.names, vg.edges[keep], vg.R_rel[keep], H=None if vg.H is None else vg.H[keep],
                    inliers=None if vg.inliers is None else vg.inliers[keep],
                    stats={k: v[keep] for k, v in vg.stats.items()}, allow_isolated=True)
    sub, _ = sub.largest_component()
    truth = read_reference(gt)
    row: dict = {"case": f"{name} (degenerate edges dropped)", "n_dropped_edges": int(flag.sum()),
                 "dropped_pairs": [[vg.names[i], vg.names[j]] for i, j in vg.edges[flag]], "methods": {}}
    for spec in load_configs(None, tokens)[2]:
        r = average(sub, spec.name, spec.config)
        R_ref, mask = match_reference(r.names, truth.names, truth.R)
        s = summarize(r.R, R_ref, mask)
        row["methods"][spec.label] = {k: s[k] for k in ("n_evaluated", "median_deg", "mean_deg", "rms_deg", "max_deg")}
        row["methods"][spec.label].update({"n_cameras": len(r.names), "time_s": r.time_s,
                                           **{k: r.stats[k] for k in ("certified", "rank") if k in r.stats}})
    return row


def anisotropy(r: dict) -> dict | None:
    """SDP-cSO(3) vs SDP-O(3)-ISO and IRLS-H-ℓ½ vs IRLS-ℓ½ of one case, where it has all four."""
    ms = {**r["methods"], **r.get("extra_methods", {})}
    if not {"sdp-cso3", "sdp-o3-iso", "irls-l0.5", "irls-h-l0.5"} <= set(ms):
        return None
    c, i, l, h = ms["sdp-cso3"], ms["sdp-o3-iso"], ms["irls-l0.5"], ms["irls-h-l0.5"]

    def less(a, b):
        return a is not None and b is not None and a < b

    return {"cso3_median_deg": c["median_deg"], "o3_iso_median_deg": i["median_deg"],
            "irls_median_deg": l["median_deg"], "irls_h_median_deg": h["median_deg"],
            "cso3_rms_deg": c["rms_deg"], "o3_iso_rms_deg": i["rms_deg"], "irls_rms_deg": l["rms_deg"],
            "irls_h_rms_deg": h["rms_deg"],
            "cso3_certified": c.get("certified"), "o3_iso_certified": i.get("certified"),
            "pays_sdp_median": less(c["median_deg"], i["median_deg"]),
            "pays_sdp_rms": less(c["rms_deg"], i["rms_deg"]),
            "pays_irls_median": less(h["median_deg"], l["median_deg"]),
            "pays_irls_rms": less(h["rms_deg"], l["rms_deg"])}


def table(rows: list[dict]) -> str:
    head = (f"{'case':<13} {'row':<20} {'cams':>7} {'median°':>8} {'mean°':>8} {'rms°':>8} {'max°':>8} "
            f"{'time s':>8} {'vs incr°':>8} {'vs glo°':>8}  note")
    lines = [head, "-" * len(head)]
    for r in rows:
        ms = {**r["methods"], **{f"{k} *": v for k, v in r.get("extra_methods", {}).items()}}
        for label, s in ms.items():
            cams = f"{s.get('n_evaluated') or 0}/{s.get('n_cameras') or r.get('n_cameras_graph') or '?'}"
            lines.append(f"{r['case']:<13} {label:<20} {cams:>7} {_f(s.get('median_deg'))} {_f(s.get('mean_deg'))} "
                         f"{_f(s.get('rms_deg'))} {_f(s.get('max_deg'))} {_f(s.get('time_s'), 2)} "
                         f"{_f(s.get('vs_pycolmap_median_deg'))} {_f(s.get('vs_glomap_median_deg'))}  {_note(s)}")
        for p, s in r.get("peers", {}).items():
            cams = f"{s.get('n_evaluated') or 0}/{s.get('n_images') or '?'}"
            other = s.get("vs_peers_median_deg") or {}
            lines.append(f"{r['case']:<13} {PEER_TITLE.get(p, p):<20} {cams:>7} {_f(s.get('median_deg'))} "
                         f"{_f(s.get('mean_deg'))} {_f(s.get('rms_deg'))} {_f(s.get('max_deg'))} "
                         f"{_f(s.get('time_s'), 2)} {_f(other.get('pycolmap'))} {_f(other.get('glomap'))}  "
                         f"registered {s.get('n_registered')}/{s.get('n_images')}, {s.get('n_models')} model(s)")
        if "stages" not in r:
            continue
        st = r["stages"]
        lines.append(f"{'':<13} our path: to rotations {r['our_path_rotations_s']:.1f} s (features→averaging; "
                     f"averaging {st.get('averaging', 0):.2f} s), with refine {r['our_path_s']:.1f} s "
                     f"(refine {st.get('refine', 0):.2f} s)")
        for p, s in r.get("peers", {}).items():
            t = s.get("times") or {}
            tr = r["time_ratios"]
            lines.append(f"{'':<13} {PEER_TITLE.get(p, p)}: {_g(s.get('time_s'))} s "
                         f"(extract {_g(t.get('extract_s'))} + "
                         f"match {_g(t.get('match_s'))} + map {_g(t.get('map_s'))}); ratio ours/peer: to rotations "
                         f"{_g(tr.get(f'rotations_over_{p}'), 2)}, "
                         f"with refine {_g(tr.get(f'with_refine_over_{p}'), 2)}")
    lines.append("* a row of the untimed second run (default methods + " + ", ".join(EXTRA_METHODS) + ")")
    return "\n".join(lines)


def _note(s: dict) -> str:
    """A method row's verdict in a few words: the SDP's certificate, a local method's check, a refinement's status."""
    if "n_refined" in s:
        return f"refine {s.get('status')}, {s['n_refined']}/{s.get('n_cameras')} refined"
    if "certified" in s:
        return "certified" if s["certified"] else "NOT certified"
    return s.get("certificate_verdict") or ""


def _f(v, nd: int = 3) -> str:
    try:
        return f"{float(v):>8.{nd}f}"
    except (TypeError, ValueError):
        return f"{'–':>8}"


def _g(v, nd: int = 1) -> str:
    try:
        return f"{float(v):.{nd}f}"
    except (TypeError, ValueError):
        return "–"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="default scene and one rendered scene only")
    ap.add_argument("--only", default="", help="comma-separated subset: default,fountain,temple,rendered")
    ap.add_argument("--keep", type=Path, default=None, help="keep the run folders here (default: a temp folder)")
    a = ap.parse_args(argv)
    only = set(filter(None, a.only.split(","))) or {"default", "fountain", "temple", "rendered"}
    if a.quick:
        only &= {"default", "rendered"}
    from pipeline import run  # noqa: PLC0415

    work_root = a.keep or Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    if a.keep is None:  # a temp folder of runs is removed at exit (--keep keeps them)
        atexit.register(shutil.rmtree, work_root, True)
    prev = json.loads(RESULTS.read_text()) if RESULTS.exists() and a.only else {}
    # with --only, the other cases are kept from the results file (of this format: "rows")
    rows: dict[str, dict] = {r["case"]: r for r in prev.get("rows", [])}
    if "default" in only:
        # exactly `python run.py`: the default rendered scene, default methods, both peers
        rows["default"] = run_case(run, "default", None, None, None, work_root)
    fountain = DATA / "strecha" / "fountain-P11"
    if "fountain" in only:
        if fountain.is_dir():
            rows["fountain-P11"] = run_case(run, "fountain-P11", fountain / "images", fountain / "gt_dense_cameras",
                                            fountain / "images" / "K.txt", work_root)
        else:
            print(f"skipping fountain-P11: {fountain} not found")
    temple = DATA / "middlebury-templeSparseRing"
    if "temple" in only:
        if temple.is_dir():
            par = temple / "templeSR_par.txt"
            rows["temple"] = run_case(run, "temple", temple, par, par, work_root)
            tokens = [k for k in rows["temple"]["methods"] if not k.endswith(REFINE_SUFFIX)] + EXTRA_METHODS
            extra = without_degenerate("temple", work_root / "temple", par, tokens)
            if extra is not None:
                rows[extra["case"]] = extra
            else:
                rows.pop("temple (degenerate edges dropped)", None)
                print("  temple: no pair of the view graph is flagged degenerate; no row without them", flush=True)
        else:
            print(f"skipping temple: {temple} not found")
    if "rendered" in only:
        from pipeline.synthetic.render import SceneConfig, render_scene

        seeds = [1] if a.quick else [1, 2, 3]
        for s in seeds:
            scene = work_root / f"scene{s}"
            # 12 views with pixel noise: the anisotropy comparison needs noisy, unequal pairs
            render_scene(12, s, scene, config=SceneConfig(noise_sigma=2.0, arc_deg=100.0))
            rows[f"rendered-{s}"] = run_case(run, f"rendered-{s}", scene, scene / "cameras.txt", None, work_root)
    cases = list(rows.values())
    for r in cases:
        aniso = anisotropy(r)
        if aniso is not None:
            r["anisotropy"] = aniso
    save_results(RESULTS, cases, "end_to_end.py", argv)
    print(table(cases))
    print("\nanisotropy: SDP-cSO(3) vs SDP-O(3)-ISO, IRLS-H-ℓ½ vs IRLS-ℓ½ (median / RMS degrees vs truth)")
    for r in cases:
        x = r.get("anisotropy")
        if x:
            print(f"  {r['case']:<34} cSO3 {_f(x['cso3_median_deg'])} /{_f(x['cso3_rms_deg'])}   "
                  f"ISO {_f(x['o3_iso_median_deg'])} /{_f(x['o3_iso_rms_deg'])}   "
                  f"IRLS-H {_f(x['irls_h_median_deg'])} /{_f(x['irls_h_rms_deg'])}   "
                  f"IRLS {_f(x['irls_median_deg'])} /{_f(x['irls_rms_deg'])}   pays (median, SDP / IRLS): "
                  f"{x['pays_sdp_median']} / {x['pays_irls_median']}")
    for r in cases:
        for label, s in {**r["methods"], **r.get("extra_methods", {})}.items():
            for p in PEERS:
                o = s.get(f"on_{p}_images")
                if o:
                    print(f"  {r['case']}: {label} on {PEER_TITLE[p]}'s {o['n_evaluated']} registered images: median "
                          f"{_g(o['median_deg'], 3)}, max {_g(o['max_deg'], 3)} ({PEER_TITLE[p]} "
                          f"{_g(r['peers'][p]['median_deg'], 3)})")
        for p, s in r.get("peers", {}).items():
            for nm, why in (s.get("unregistered") or {}).items():
                print(f"  {r['case']}: {PEER_TITLE.get(p, p)} did not register {nm}: {why}")
        left = r.get("left_out_by_view_graph") or {}
        for nm, why in (left.items() if isinstance(left, dict) else ((n, "") for n in left)):
            print(f"  {r['case']}: our view graph left out {nm}: {why}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
