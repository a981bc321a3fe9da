"""The method registry: tokens, labels, options from YAML and overrides, defaults, and a new method in one line."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline import run  # noqa: E402
from pipeline.averaging import Method, average, register, unregister  # noqa: E402
from pipeline.averaging.cli import main_cli  # noqa: E402
from pipeline.averaging.init import initial_rotations  # noqa: E402
from pipeline.averaging.colmap_ra import have_pycolmap
from pipeline.averaging.registry import (  # noqa: E402
    default_methods,
    get_method,
    method_config_from,
    parse_method,
    parse_methods,
)
from pipeline.averaging.result import AveragingResult, method_config, start_of  # noqa: E402
from pipeline.core import so3  # noqa: E402
from pipeline.core.config import Config, option, stage_config  # noqa: E402
from pipeline.core.errors import ConfigError, PipelineError, ViewGraphError  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.io.rotations import read_rotations  # noqa: E402
from pipeline.plan import RunConfig  # noqa: E402
from pipeline.synthetic.graphs import paper2_graph  # noqa: E402
from pipeline.synthetic.render import SceneConfig, render_scene  # noqa: E402


# ------------------------------------------------------------------------ tokens
def test_parse_method():
    assert parse_method("irls").label == "irls-l0.5"
    spec = parse_method("irls-geman-mcclure")
    assert spec.name == "irls" and spec.config.loss == "geman-mcclure" and spec.label == "irls-geman-mcclure"
    assert parse_method("sdp").config.variant == "cso3" and parse_method("sdp").label == "sdp-cso3"
    assert parse_method("sdp-o3-iso").config.variant == "o3-iso"
    assert parse_method("l1").name == "l1" and parse_method("l1").label == "l1"
    assert parse_method("weiszfeld").label == "weiszfeld"
    spec = parse_method("irls-h")
    assert spec.name == "irls-h" and spec.config.loss == "l0.5" and spec.label == "irls-h-l0.5"
    assert parse_method("irls-h-cauchy").label == "irls-h-cauchy"
    # the longest name wins only with its dash: irls-huber is irls with Huber's loss
    assert (parse_method("irls-huber").name, parse_method("irls-huber").config.loss) == ("irls", "huber")
    # a bare loss is the default method's
    assert parse_method("huber").label == "irls-huber" and parse_method(" L2 ").label == "irls-l2"
    assert parse_method("irls-l1/2").label == "irls-l1_2"  # labels name files


def test_parse_method_rejects_unknown():
    with pytest.raises(PipelineError, match="unknown SDP variant"):
        parse_method("sdp-so4")
    with pytest.raises(PipelineError, match="unknown method"):
        parse_method("irls-nosuchloss")
    with pytest.raises(PipelineError, match="unknown method"):
        parse_method("irls-h-nosuchloss")
    with pytest.raises(ConfigError, match="unknown method 'nope': unknown loss 'nope'.*methods are irls, irls-<loss>"):
        parse_method("nope")


def test_parse_methods_splits_commas_dedupes_and_accepts_a_scalar():
    specs = parse_methods(["irls,sdp", "irls-l0.5", "weiszfeld"])
    assert [s.label for s in specs] == ["irls-l0.5", "sdp-cso3", "weiszfeld"]
    assert [s.label for s in parse_methods("irls, l1")] == ["irls-l0.5", "l1"]
    assert parse_methods(None) == [] and parse_methods([]) == []


def test_methods_scalar_in_yaml_is_one_method(tmp_path):
    """``methods: irls`` written as a scalar is one method, not the letters i, r, l, s."""
    p = tmp_path / "c.yaml"
    p.write_text("run:\n  methods: irls\n")
    from pipeline.core.config import load_yaml

    rcfg = stage_config(RunConfig, load_yaml(p), "run")
    assert rcfg.methods == ("irls",)
    assert [s.label for s in parse_methods(rcfg.methods)] == ["irls-l0.5"]


# ---------------------------------------------------------------------- options
def test_options_from_yaml_sections_subsections_tokens_and_overrides():
    yaml = {"averaging": {"alpha_deg": 3.0, "tol_rad": 1e-4, "irls-h": {"tol_rad": 1e-6}},
            "sdp": {"eps_abs": 1e-6}}
    irls = parse_method("irls", yaml).config
    assert irls.alpha_deg == 3.0 and irls.tol_rad == 1e-4  # flat keys of the section apply to its methods
    assert parse_method("irls-h", yaml).config.tol_rad == 1e-6  # a method's own mapping beats the section
    assert parse_method("weiszfeld", yaml).config.tol_rad == 1e-4
    sdp = parse_method("sdp", yaml).config
    assert sdp.eps_abs == 1e-6 and sdp.max_iterations is None  # averaging: keys do not reach the sdp section
    # the token beats YAML; the caller's overrides beat the token
    yaml2 = {"averaging": {"loss": "cauchy"}}
    assert parse_method("irls", yaml2).label == "irls-cauchy"
    assert parse_method("irls-huber", yaml2).config.loss == "huber"
    assert parse_method("sdp-o3-iso", {}, {"sdp": {"variant": "cso3", "solver": "clarabel"}}).config.solver == "clarabel"
    assert parse_method("irls", {}, options={"loss": "l2"}).label == "irls-l2"


@pytest.mark.parametrize("yaml, match", [
    ({"averaging": {"alpah_deg": 5}}, r"^\[averaging\]: unknown key\(s\) \['alpah_deg'\]; allowed keys are \[.*'alpha_deg'"),
    ({"sdp": {"max_iters": 5}}, r"^\[sdp\]: unknown key\(s\) \['max_iters'\]; allowed keys are \[.*'max_iterations'"),
    ({"averaging": {"irls": {"alpha": 2}}}, r"unknown key\(s\) \['alpha'\]; allowed keys are \[.*'alpha_deg'"),
    ({"averaging": {"irls": 5}}, r"irls: expected a mapping"),
    ({"averaging": ["irls"]}, r"\[averaging\]: expected a mapping"),
    ({"averaging": {"irls-h": {"alpha_sigma": -1}}}, r"alpha_sigma=-1.* > 0"),
    ({"averaging": {"max_iterations": "many"}}, r"max_iterations='many' but expected an integer"),
])
def test_bad_yaml_options_are_one_line_errors_naming_the_allowed_keys(yaml, match):
    with pytest.raises(ConfigError, match=match) as e:
        parse_methods(["irls", "irls-h"], yaml)
    assert "\n" not in str(e.value)


def test_default_methods_are_checked_before_any_work():
    with pytest.raises(ConfigError, match="loss"):  # irls, a default, gets a bad loss
        parse_methods([], {"averaging": {"loss": "nope"}})


def test_option_of_another_method_is_rejected():
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['loss'\]; allowed keys are \[.*'variant'"):
        parse_method("sdp", options={"loss": "huber"})


def test_default_methods_follow_H_and_size():
    g = paper2_graph(8, 0.6, seed=0)
    no_H = g.vg.with_H(None)

    @dataclass
    class RunCfg:
        sdp_max_n: int = 60

    labels = lambda specs: [s.label for s in specs]  # noqa: E731
    # colmap-ra, COLMAP's averaging on the same graph, runs beside ours (pycolmap is a dependency: always there)
    assert have_pycolmap()
    colmap, why = ["colmap-ra"], []
    specs, notes = default_methods(g.vg, RunCfg())
    assert labels(specs) == ["irls-l0.5", "irls-h-l0.5", "sdp-cso3"] + colmap and notes == why
    specs, notes = default_methods(no_H, RunCfg())
    assert labels(specs) == ["irls-l0.5"] + colmap and notes == why
    specs, notes = default_methods(g.vg, RunCfg(sdp_max_n=5))
    assert labels(specs) == ["irls-l0.5", "irls-h-l0.5"] + colmap and notes == ["SDP-cSO(3) not run by default: N=8 > "
                                                                                "run.sdp_max_n=5"] + why


def test_sdp_needs_H_only_for_anisotropic_variants():
    sdp = get_method("sdp")
    assert sdp.requires_H(parse_method("sdp").config) and not sdp.requires_H(parse_method("sdp-cso3-iso").config)
    assert get_method("irls-h").requires_H(parse_method("irls-h").config)
    assert not get_method("irls").requires_H(parse_method("irls").config)


def test_average_checks_method_H_and_start():
    g = paper2_graph(6, 0.8, seed=1)
    with pytest.raises(ViewGraphError, match="'sdp-cso3' needs a view graph with H"):
        average(g.vg.with_H(None), "sdp")
    with pytest.raises(ConfigError, match="takes no start"):
        average(g.vg, "sdp", init=g.R_true)
    with pytest.raises(ConfigError, match="unknown method 'toy'"):
        average(g.vg, "toy")
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['alpha'\]"):
        average(g.vg, "irls", alpha=3.0)


def test_register_checks_its_entry():
    cfg = get_method("irls").config_cls
    with pytest.raises(ValueError, match="already registered"):
        register(Method("irls", cfg, average))
    with pytest.raises(ValueError, match="lower case"):
        register(Method("My Method", cfg, average))
    with pytest.raises(ValueError, match=r"has no field\(s\) \['variant'\]"):
        register(Method("x", cfg, average, token_option="variant"))
    with pytest.raises(ValueError, match="is an option of"):
        register(Method("loss", cfg, average))
    with pytest.raises(TypeError, match="Config subclass"):
        register(Method("x", dict, average))  # type: ignore[arg-type]


def test_method_config_of_a_call():
    cfg = method_config(get_method("irls").config_cls, None, {"loss": "l2"}, "random", bare={"refine": False})
    assert (cfg.loss, cfg.init, cfg.refine) == ("l2", "random", False)
    assert method_config(type(cfg), cfg, {}) is cfg
    assert method_config(type(cfg), cfg, {"alpha_deg": 2}).alpha_deg == 2.0
    with pytest.raises(ConfigError, match="expected a IRLSConfig"):
        method_config(type(cfg), get_method("l1").config_cls(), {})
    assert start_of(None, cfg) == "random" and start_of(np.eye(3)[None], cfg).shape == (1, 3, 3)


# ------------------------------------------------- acceptance: a method in one line
@dataclass(frozen=True, kw_only=True)
class ToyConfig(Config):
    """A toy method: the spanning-tree start alone."""

    SECTION = "averaging.toy"
    tree: Literal["mst", "random"] = option("mst", "spanning tree: mst or random")
    seed: int = option(0, "seed of the random tree", ge=0)


def solve_toy(vg: ViewGraph, config: ToyConfig | None = None, *, init: Any = None, init_weights: Any = None,
              **options: Any) -> AveragingResult:
    cfg = method_config(ToyConfig, config, options)
    R = initial_rotations(vg, cfg.tree if init is None else init, weights=init_weights, seed=cfg.seed)
    return AveragingResult(method=f"toy-{cfg.tree}", names=list(vg.names), R=R, time_s=0.0,
                           edge_index=np.arange(vg.n_edges), stats={"tree": cfg.tree})


@pytest.fixture
def toy():
    register(Method("toy", ToyConfig, solve_toy, help="the spanning-tree start alone"))  # THE one registry line
    yield
    unregister("toy")


def _graph_file(tmp_path):
    rng = np.random.default_rng(0)
    R = so3.random_rotations(7, rng)
    e = np.array([(i, j) for i in range(7) for j in range(i + 1, 7) if j - i <= 2])
    vg = ViewGraph.from_absolute([f"im{i}.png" for i in range(7)], R, e)
    path = tmp_path / "vg.npz"
    vg.save(path)
    return path, vg, R


def test_toy_method_through_the_command(toy, tmp_path, capsys):
    path, vg, R = _graph_file(tmp_path)
    out = tmp_path / "toy.txt"
    assert main_cli([str(path), "--method", "toy", "--tree", "random", "--seed", "3", "--out", str(out), "-q"]) == 0
    names, R_est = read_rotations(out)
    assert names == vg.names
    G = so3.chordal_mean(np.swapaxes(R, 1, 2) @ R_est)
    assert np.rad2deg(so3.angle_between(R_est, R @ G)).max() < 1e-6  # exact edges: any tree is exact
    stats = json.loads(out.with_suffix(".json").read_text())
    assert stats["method"] == "toy-random" and stats["options"] == {"tree": "random", "seed": 3}
    capsys.readouterr()
    # the command's --help lists it and its option
    with pytest.raises(SystemExit):
        main_cli(["--help"])
    text = capsys.readouterr().out
    assert "toy" in text and "--tree" in text
    # an option the toy has not is refused in one line
    assert main_cli([str(path), "--method", "toy", "--loss", "l2", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: [averaging.toy]: unknown key(s) ['loss']") and "\n" not in err


@pytest.mark.slow
def test_toy_method_through_run_py(toy, tmp_path):
    scene = tmp_path / "scene"
    render_scene(5, 0, scene, config=SceneConfig(width=320, height=240, focal=280.0, supersample=1))
    cfg = tmp_path / "toy.yaml"
    cfg.write_text("run:\n  methods: toy\n  plots: false\naveraging:\n  toy:\n    tree: random\n")
    m = json.loads(run.main(scene, tmp_path / "out", config=cfg, gt=scene / "cameras.txt", reference=False,
                            quiet=True).read_text())
    assert list(m["methods"]) == ["toy", "toy+refine"]  # the refinement starts from the only method
    toy_m = m["methods"]["toy"]
    assert toy_m["method"] == "toy-random" and toy_m["n_evaluated"] == 5 and toy_m["median_deg"] < 2.0
    assert (tmp_path / "out" / "rotations" / "toy.record.json").is_file()
    assert "| toy |" in (tmp_path / "out" / "report.md").read_text()


def test_run_py_unknown_averaging_key_is_one_line_before_any_work(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("averaging:\n  alpah_deg: 3\n")
    out = tmp_path / "out"
    assert run.main_cli(["--out", str(out), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: [averaging]: unknown key(s) ['alpah_deg']; allowed keys are [") and "\n" not in err
    assert "'alpha_deg'" in err and "TypeError" not in err
    assert not out.exists()


def test_method_config_from_checks_strictly():
    with pytest.raises(ConfigError, match=r"\[averaging.l1\]: unknown key\(s\) \['loss'\]"):
        method_config_from("l1", {"averaging": {"l1": {"loss": "l2"}}})
    assert method_config_from("l1", {"averaging": {"loss": "l2"}}).max_iterations == 100  # not an l1 option: skipped
