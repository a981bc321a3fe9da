"""``python -m pipeline.average``: average one view graph with one registered method.

Usage::

    python -m pipeline.average INPUT [--method M] [--init mst|random|FILE] [--config YAML]
        [--rotation-tol T] [method options ...] --out ROTATIONS [--json STATS] [--overwrite] [-v | -q]

INPUT is any view graph of :mod:`pipeline.io.graphs`: a ``.npz``, a ``.mat`` (LU Sphinx
or ℓ1 layout), a 1DSfM folder, a ``.g2o`` file or GLOMAP relative poses; input
rotations within ``--rotation-tol`` (1e-3) of SO(3) are projected with one warning.
M is a method or token of the registry (``irls``, ``irls-<loss>``, ``irls-h``, ``l1``,
``weiszfeld``, ``sdp``, ``sdp-<variant>``, ``colmap-ra``, ...). The method options are the fields of the methods' typed
configs (one flag each, shared by the methods that have the option); ``--config``
reads the ``averaging:`` and ``sdp:`` sections of a YAML file as ``run.py`` does,
and the flags override it.

Outputs: ROTATIONS (:mod:`pipeline.io.rotations`), its stats beside it
(``ROTATIONS`` with the suffix ``.json``; also copied to ``--json STATS``) and its
record (``.record.json``). A re-run with the same method, options and input reuses
an intact result unless ``--overwrite``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from pipeline.averaging.registry import DEFAULT_METHOD, check_sections, methods, parse_method, tokens_help
from pipeline.averaging.stage import AveragingStage
from pipeline.core.atomic import check_writable, write_json
from pipeline.core.cli import add_config_args, run_cli
from pipeline.core.config import load_yaml
from pipeline.core.errors import ConfigError, InputFileError
from pipeline.io.graphs import FORMATS, can_hold_precisions, check_input, input_files
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL

__all__ = ["main", "main_cli", "build_parser"]

_START_KINDS = ("mst", "random")


def main(input_path: str | Path, out_path: str | Path, json_path: str | Path | None = None,
         overwrite: bool = False, method: str = DEFAULT_METHOD, init: str | Path | None = None,
         config_path: str | Path | None = None, rotation_tol: float = DEFAULT_ROTATION_TOL, **options: Any) -> Path:
    """Read a view graph, average it, write rotations and stats atomically (reused when intact).

    Args:
        input_path: a view graph (:mod:`pipeline.io.graphs`).
        out_path: rotations text file to write.
        json_path: optional copy of the stats.
        overwrite: recompute even if an intact result with the same options exists.
        method: a registered method or token (``irls``, ``irls-huber``, ``sdp-o3-iso``).
        init: ``"mst"``, ``"random"`` or a rotations file to start from.
        config_path: a YAML file whose ``averaging:``/``sdp:`` sections give options.
        rotation_tol: input rotations within this of SO(3) are projected (one warning).
        **options: fields of the method's config (``loss``, ``alpha_deg``, ...), on top.

    Returns:
        ``out_path``.
    """
    input_path, out_path = Path(input_path), Path(out_path)
    check_input(input_path)  # a missing input, a plain folder: one line, before the stage fingerprints it
    if not (rotation_tol >= 0 and rotation_tol < 1):
        raise ConfigError(f"--rotation-tol {rotation_tol!r}; expected a distance from SO(3) in [0, 1), e.g. 1e-3")
    if out_path.suffix.lower() == ".json":
        raise ConfigError(f"--out {out_path} is the rotations text file (e.g. rotations.txt); its stats go beside "
                          "it as .json")
    for flag, path in (("--out", out_path), ("--json", json_path)):  # found before the work, not when writing
        if path is not None and Path(path).is_dir():
            raise InputFileError(f"{flag} {path} is a folder; pass a file name in it (e.g. {Path(path) / 'x'}"
                                 f"{'.txt' if flag == '--out' else '.json'})")
    inputs = {f.resolve() for f in input_files(input_path)}
    for flag, path in (("--out", out_path), ("--json", json_path)):  # read first, then replaced: lost
        if path is not None and Path(path).resolve() in inputs:
            raise InputFileError(f"{flag} {path} would overwrite the input {input_path}; write it to another file")
    init_file = None
    if init is not None and str(init) in _START_KINDS:
        options["init"] = str(init)
    elif init is not None:
        init_file = Path(init)
        if not init_file.is_file():
            raise InputFileError(f"--init {str(init)!r} is neither 'mst', 'random' nor an existing rotations file")
    yaml_data = load_yaml(config_path)
    check_sections(yaml_data)
    spec = parse_method(method, yaml_data, options={k: v for k, v in options.items() if v is not None})
    if spec.method.requires_H(spec.config) and not can_hold_precisions(input_path):  # known before reading
        raise ConfigError(f"method {spec.label!r} needs a view graph with H (two-view BA precisions), and "
                          f"{input_path} cannot hold H (a 1DSfM folder or GLOMAP text); give an .npz, .mat or .g2o "
                          "with H, or use a method without H (e.g. 'irls')")
    if init_file is not None and not spec.method.takes_init:
        raise ConfigError(f"method {spec.name!r} takes no start; drop --init")
    if json_path is not None:  # --out's folder the stage checks before its work; --json's here, before it too
        check_writable(Path(json_path).parent, f"--json {json_path}")
    label = out_path.name[: -len(out_path.suffix)] if out_path.suffix else out_path.name
    stage = AveragingStage(out_path.parent, spec, input_path, label=label, rotations=out_path, init=init_file,
                           rotation_tol=rotation_tol)
    stage.run(overwrite)
    if json_path is not None and Path(json_path).resolve() != stage.stats_path.resolve():
        write_json(json_path, json.loads(stage.stats_path.read_text(encoding="utf-8")))
    return out_path


def build_parser() -> argparse.ArgumentParser:
    """The parser: fixed arguments, then one option per field of the registered methods' configs."""
    listing = "\n".join(f"  {m.name:<10} {m.help}\n  {'':<10} options: {', '.join(m.fields())}" for m in methods())
    p = argparse.ArgumentParser(
        prog="python -m pipeline.average", description="Average one view graph with one registered method.",
        epilog=f"methods:\n{listing}\n\nAn option shared by several methods is listed once, under the first; "
               "each method keeps its own default\n(e.g. --max-iterations: irls 100, l1 100).",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", type=Path, help=FORMATS)
    p.add_argument("--method", default=DEFAULT_METHOD, metavar="M",
                   help=f"{tokens_help()} (default {DEFAULT_METHOD})")
    p.add_argument("--init", default=None, help="mst | random | a rotations file (default: the method's, mst)")
    p.add_argument("--config", type=Path, default=None, help="YAML file with averaging:/sdp: sections (as run.py)")
    p.add_argument("--rotation-tol", type=float, default=DEFAULT_ROTATION_TOL, metavar="T",
                   help=f"project input rotations within T of SO(3) (max|RᵀR−I|), refuse beyond (default "
                        f"{DEFAULT_ROTATION_TOL:g})")
    p.add_argument("--out", type=Path, required=True, help="rotations text file to write")
    p.add_argument("--json", type=Path, default=None, help="also write the stats JSON here")
    p.add_argument("--overwrite", action="store_true", help="recompute even if the result is up to date")
    seen = {"init"}
    for m in methods():
        new = [f for f in m.fields() if f not in seen]
        if new:
            shared = sorted(set(m.fields()) & seen - {"init"})
            add_config_args(p, m.config_cls, exclude=sorted(seen),
                            group=f"options of {m.name}" + (f" (also: {', '.join(shared)})" if shared else ""))
        seen |= set(m.fields())
    return p


def main_cli(argv: list[str] | None = None) -> int:
    def body(a: argparse.Namespace) -> int:
        opts = {k[len("cfg__"):]: v for k, v in vars(a).items() if k.startswith("cfg__") and v is not None}
        print(main(a.input, a.out, a.json, overwrite=a.overwrite, method=a.method, init=a.init,
                   config_path=a.config, rotation_tol=a.rotation_tol, **opts))
        return 0

    return run_cli(body, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main_cli())
