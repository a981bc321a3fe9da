"""The refinement alone, run again on copies of kept run folders: what a change to the refine stage does to them.

    python benchmarks/refine_again.py RUN [RUN ...] --label LABEL [--json J] [-- REFINE OPTIONS ...]

Each RUN is an ``OUT`` folder of ``run.py`` (``--keep`` of ``real_photos.py``, ``refine.py``, ...) run with a truth
(``metrics.json``'s ``input.gt``). It is copied to a temporary folder, ``python -m pipeline.refine --out COPY
--overwrite [REFINE OPTIONS]`` runs there in a fresh process (the code on ``PYTHONPATH`` or the installed one: run
it once with an older checkout on ``PYTHONPATH`` for a "before" label), and the refined rotations are scored
against the truth (median error after the ℓ2 alignment, on the images refined or placed). Nothing in RUN is
changed.

Reported per run: the refined median and count, the refine stage's own time and the process's wall time, and the
principal-point probe's ratio and decision where it ran. Rows go to ``--json`` (default
``benchmarks/results/refine_again.json``) under ``LABEL``, with the code's commit; other labels are kept.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "refine_again.json"

SCORE = """
import json, sys
from pathlib import Path
import numpy as np
import pipeline
from pipeline.evaluation.metrics import rotation_errors_deg
from pipeline.io.rotations import read_rotations
from pipeline.reference.truth import read_reference
out = Path(sys.argv[1])
gt = read_reference(json.loads((out / "metrics.json").read_text())["input"]["gt"])
stem = {Path(n).stem: i for i, n in enumerate(gt.names)}
path = next((out / "rotations").glob("*+refine.txt"))
names, R = read_rotations(path)
e = rotation_errors_deg(R, gt.R[[stem[Path(n).stem] for n in names]])
rec = json.loads(path.with_suffix(".json").read_text())
probe = rec.get("principal_point_probe") or {}
print(json.dumps({"median_deg": float(np.nanmedian(e)), "n_scored": int(np.isfinite(e).sum()),
                  "status": rec.get("status"), "refine_s": rec.get("time_s"), "probe_ratio": probe.get("ratio"),
                  "probe_decision": probe.get("decision"), "code": str(Path(pipeline.__file__).parent)}))
"""


def commit_of(code: Path) -> str:
    """The git commit of the checkout holding ``code`` (a package folder), or ``unknown``."""
    try:
        return subprocess.run(["git", "-C", str(code), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def again(run: Path, work: Path, options: list[str]) -> dict:
    """The refine stage on a copy of ``run`` in ``work``; its scores (see the module docstring)."""
    copy = work / "run"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(run, copy, symlinks=True)
    cmd = [sys.executable, "-m", "pipeline.refine", "--out", str(copy), "--overwrite", *options]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=work)  # not this folder: -m would import its code
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        return {"run": str(run), "error": (done.stderr.strip().splitlines() or ["?"])[-1][:200], "wall_s": wall}
    scored = subprocess.run([sys.executable, "-c", SCORE, str(copy)], capture_output=True, text=True, check=True,
                            cwd=work)
    row = {"run": str(run), "wall_s": wall, **json.loads(scored.stdout)}
    row["commit"] = commit_of(Path(row["code"]))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", help="run.py OUT folders (with a truth)")
    ap.add_argument("--label", required=True, help="the section of the JSON the rows go to")
    ap.add_argument("--json", type=Path, default=RESULTS)
    argv = sys.argv[1:] if argv is None else argv
    cut = argv.index("--") if "--" in argv else len(argv)
    a = ap.parse_args(argv[:cut])
    options = argv[cut + 1:]  # python -m pipeline.refine's own options
    missing = [str(r) for r in a.runs if not (r / "metrics.json").is_file()]
    if missing:
        print(f"error: not run.py output folders (no metrics.json): {missing[:3]}", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory(prefix="refine_again_") as tmp:
        for run in a.runs:
            row = again(run.resolve(), Path(tmp), options)
            rows.append(row)
            print(f"  {run}: " + (f"error {row['error']}" if "error" in row else
                                  f"median {row['median_deg']:.4f}° on {row['n_scored']}, refine "
                                  f"{row['refine_s']:.1f} s (wall {row['wall_s']:.1f} s), probe {row['probe_ratio']}"),
                  flush=True)
    from pipeline.core.atomic import write_json  # noqa: PLC0415

    out = json.loads(a.json.read_text()) if a.json.is_file() else {}
    out[a.label] = {"rows": rows, "argv": argv,
                    "median_refine_s": float(np.median([r["refine_s"] for r in rows if "refine_s" in r] or [np.nan]))}
    write_json(a.json, out)
    print(f"wrote {a.json} ({a.label})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
