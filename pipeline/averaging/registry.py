"""THE averaging method registry, read by ``run.py``, ``python -m pipeline.average`` and the report.

A method is one module holding a typed config (a frozen
:class:`pipeline.core.config.Config`) and a solve function on a connected view graph,
``solve(vg, config=cfg, init=..., init_weights=...) -> AveragingResult``. Adding it to
the pipeline is one registry line::

    register(Method("toy", ToyConfig, solve_toy))

after which ``run.py --methods toy``, ``python -m pipeline.average --method toy`` (with
one option per field of ``ToyConfig``) and ``averaging: {toy: {...}}`` in YAML work.

**Tokens** (``run.py --methods``, ``python -m pipeline.average --method``): a method
name, or ``<name>-<value>`` for a method with a ``token_option`` (``irls-<loss>``,
``irls-h-<loss>``, ``sdp-<variant>``). The longest registered name wins:
``irls-h-cauchy`` is irls-h with loss cauchy, ``irls-huber`` is irls with loss huber.
A token that names no method is a loss of :data:`DEFAULT_METHOD` (``huber`` =
``irls-huber``). A method's label (its output file names, its row in the report) is
its name, followed by its token option's value when it has one (``irls-l0.5``).

**Options** of a method, lowest precedence first: its config's defaults; the keys of
its YAML section (``averaging:`` for the iterative methods, ``sdp:`` for the SDP) that
are fields of its config; its own mapping ``averaging: {<name>: {...}}`` (checked
strictly); the value its token gives; the caller's overrides (command-line options,
``run.sdp_solver``). A key of a section that no method of that section knows is an
error that names the allowed keys.

**Defaults** (``run.py`` without ``--methods``): every method whose ``default(vg,
run_config)`` is True, in registration order: IRLS-ℓ½; IRLS-H-ℓ½ when the view graph
has H; SDP-cSO(3) when it has H and at most ``run.sdp_max_n`` cameras; ``colmap-ra``
(COLMAP's rotation averaging on the same view graph, the like-for-like comparison) when
pycolmap is installed.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from pipeline.averaging.colmap_ra import ColmapRAConfig, colmap_ra, have_pycolmap
from pipeline.averaging.irls import IRLSConfig, irls
from pipeline.averaging.irls_h import IRLSHConfig, irls_h
from pipeline.averaging.l1 import L1Config, solve_l1
from pipeline.averaging.result import AveragingResult
from pipeline.averaging.sdp import VARIANTS, SdpConfig, solve_sdp
from pipeline.averaging.weiszfeld import WeiszfeldConfig, weiszfeld
from pipeline.core.config import Config
from pipeline.core.errors import ConfigError, InputFileError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["Method", "MethodSpec", "register", "unregister", "get_method", "methods", "sections",
           "parse_method", "parse_methods", "default_methods", "method_config_from", "check_sections",
           "tokens_help", "DEFAULT_METHOD", "ROOT_SECTION"]

#: The method of a bare loss token and of ``python -m pipeline.average`` without ``--method``.
DEFAULT_METHOD = "irls"
#: The YAML section whose keys may also be method names with their own options.
ROOT_SECTION = "averaging"

Overrides = Mapping[str, Mapping[str, Any]]


@dataclass(frozen=True)
class Method:
    """One averaging method.

    Attributes:
        name: the method's name (lower case, no whitespace or commas).
        config_cls: its typed options.
        solve: ``solve(vg, config=cfg[, init=..., init_weights=...]) -> AveragingResult``
            on a connected view graph.
        needs_H: whether it needs the two-view precisions H, or a function of its config.
        default: ``default(vg, run_config)``: True to run it when ``run.py`` gets no
            ``--methods``; False, or a note saying why not (it goes to the report).
        token_option: the config field that ``<name>-<value>`` sets (and the label shows).
        section: the YAML section whose keys apply to it (besides ``averaging: {<name>: ...}``).
        takes_init: ``solve`` takes ``init`` and ``init_weights`` (a start).
        error_vs_time: the report may draw its error against time (paper 1, Fig. 5c): its
            config has ``l1_iterations``, ``max_iterations`` and ``refine``, and its history
            records one ``"l1"`` or ``"irls"`` entry per iteration.
        help: one line for ``--help``.
    """

    name: str
    config_cls: type[Config]
    solve: Callable[..., AveragingResult]
    needs_H: bool | Callable[[Any], bool] = False
    default: Callable[[ViewGraph, Any], bool | str] | None = None
    token_option: str | None = None
    section: str = ROOT_SECTION
    takes_init: bool = True
    error_vs_time: bool = False
    help: str = ""

    def label(self, config: Config) -> str:
        """The method's label for ``config``: ``irls-l0.5``, ``sdp-cso3``, ``weiszfeld``."""
        if self.token_option is None:
            return self.name
        value = str(getattr(config, self.token_option)).strip().lower()
        return f"{self.name}-{re.sub(r'[^a-z0-9._+-]', '_', value)}"  # a file name: no slash (loss alias l1/2)

    def requires_H(self, config: Config) -> bool:
        return bool(self.needs_H(config) if callable(self.needs_H) else self.needs_H)

    def fields(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self.config_cls)]


@dataclass(frozen=True)
class MethodSpec:
    """One method to run with its resolved options: what ``run.py`` and the stage act on."""

    label: str
    name: str
    config: Config

    @property
    def method(self) -> Method:
        return get_method(self.name)


_REGISTRY: dict[str, Method] = {}


def register(method: Method, *, replace: bool = False) -> Method:
    """Add ``method`` to the registry (``replace`` to redefine an existing name); returns it."""
    name = method.name
    if not name or name != name.strip().lower() or any(c.isspace() or c in ",/" for c in name):
        raise ValueError(f"method name {name!r}: use lower case without whitespace, commas or slashes")
    if name in _REGISTRY and not replace:
        raise ValueError(f"method {name!r} is already registered; pass replace=True to redefine it")
    if not (isinstance(method.config_cls, type) and issubclass(method.config_cls, Config)):
        raise TypeError(f"method {name!r}: config_cls must be a pipeline.core.config.Config subclass")
    need = ([method.token_option] if method.token_option else []) + (
        ["l1_iterations", "max_iterations", "refine"] if method.error_vs_time else [])
    missing = [f for f in need if f not in method.fields()]
    if missing:
        raise ValueError(f"method {name!r}: {method.config_cls.__name__} has no field(s) {missing}")
    clash = [m.name for m in _REGISTRY.values() if name in m.fields() and m.section == ROOT_SECTION]
    if clash:
        raise ValueError(f"method name {name!r} is an option of {clash}; an averaging: key would be ambiguous")
    _REGISTRY[name] = method
    return method


def unregister(name: str) -> None:
    """Remove a method (a test's or a plugin's) from the registry."""
    _REGISTRY.pop(name, None)


def methods() -> tuple[Method, ...]:
    """Every registered method, in registration order."""
    return tuple(_REGISTRY.values())


def get_method(name: str) -> Method:
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown method {name!r}; valid methods: {', '.join(_REGISTRY)}") from None


def sections() -> tuple[str, ...]:
    """The YAML sections the methods read (``averaging``, ``sdp``)."""
    return tuple(dict.fromkeys([ROOT_SECTION] + [m.section for m in _REGISTRY.values()]))


def tokens_help() -> str:
    """``irls, irls-<loss>, irls-h, ...``: what ``--methods`` accepts."""
    out = []
    for m in _REGISTRY.values():
        out += [m.name] + ([f"{m.name}-<{m.token_option}>"] if m.token_option else [])
    return ", ".join(out)


# --------------------------------------------------------------------------- options
def _section(yaml_data: Mapping[str, Any] | None, name: str) -> dict[str, Any]:
    d = (yaml_data or {}).get(name)
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise ConfigError(f"[{name}]: expected a mapping of options, got {type(d).__name__}")
    return dict(d)


def check_sections(yaml_data: Mapping[str, Any] | None) -> None:
    """Every key of the methods' YAML sections is known, and every method's own mapping is valid.

    Raises:
        ConfigError: one line naming the unknown key(s) and the allowed ones.
    """
    for sec in sections():
        d = _section(yaml_data, sec)
        allowed = sorted({f for m in _REGISTRY.values() if m.section == sec for f in m.fields()})
        subs = list(_REGISTRY) if sec == ROOT_SECTION else []
        unknown = sorted(k for k in map(str, d) if k not in allowed and k not in subs)
        if unknown:
            raise ConfigError(f"[{sec}]: unknown key(s) {unknown}; allowed keys are {allowed}"
                              + (f", or a method name with its own options: {subs}" if subs else ""))
        for name in [k for k in d if k in subs]:
            method_config_from(name, yaml_data)


def method_config_from(name: str, yaml_data: Mapping[str, Any] | None = None, token_value: str | None = None,
                       overrides: Mapping[str, Any] | None = None) -> Config:
    """The config of method ``name`` from YAML, a token's value and overrides (module docstring)."""
    m = get_method(name)
    fields = set(m.fields())
    data = {k: v for k, v in _section(yaml_data, m.section).items() if k in fields}
    own = _section(yaml_data, ROOT_SECTION).get(name)
    if own is not None:
        if not isinstance(own, Mapping):
            raise ConfigError(f"[{ROOT_SECTION}] {name}: expected a mapping of {name}'s options, "
                              f"got {type(own).__name__}")
        data.update(own)
    if token_value is not None:
        data[m.token_option] = token_value  # type: ignore[index]
    data.update(overrides or {})
    where = f"[{ROOT_SECTION}.{name}]"
    try:
        return m.config_cls.from_dict(data, where=where)
    except ConfigError as exc:  # a value checked by what it names (a loss), not by the option: say where, if YAML
        if str(exc).startswith("[") or token_value is not None or overrides:
            raise
        raise ConfigError(f"{where} {exc}") from None


# ---------------------------------------------------------------------------- tokens
def _split(token: str) -> tuple[str, str | None]:
    """``(method name, token value or None)`` of a lower-case token."""
    best = max((n for n in _REGISTRY if token == n or (token.startswith(n + "-") and _REGISTRY[n].token_option)),
               key=len, default=None)
    if best is None:
        return DEFAULT_METHOD, token
    return best, token[len(best) + 1:] or None


def parse_method(token: str, yaml_data: Mapping[str, Any] | None = None, overrides: Overrides | None = None,
                 options: Mapping[str, Any] | None = None) -> MethodSpec:
    """The spec of one token (module docstring); a bad token is one :class:`ConfigError` line.

    Args:
        token: ``irls``, ``irls-huber``, ``sdp-o3-iso``, ...
        yaml_data: loaded YAML (``{section: {key: value}}``).
        overrides: ``{method name: {option: value}}``, above the token.
        options: options for whichever method the token names (a command line), on top.
    """
    t = str(token).strip().lower()
    name, value = _split(t)
    m = get_method(name)
    if value is not None:
        try:
            m.config_cls.from_dict({m.token_option: value})  # the token alone, so YAML errors are not blamed on it
        except (ConfigError, TypeError) as exc:
            raise ConfigError(f"unknown method {token!r}: {' '.join(str(exc).split())}; "
                              f"methods are {tokens_help()}") from None
    cfg = method_config_from(name, yaml_data, value, {**(overrides or {}).get(name, {}), **(options or {})})
    return MethodSpec(m.label(cfg), name, cfg)


def parse_methods(tokens: str | Iterable[str] | None, yaml_data: Mapping[str, Any] | None = None,
                  overrides: Overrides | None = None) -> list[MethodSpec]:
    """Specs of ``--methods`` tokens (each may hold several, comma-separated); empty: the defaults apply.

    Checks the methods' YAML sections in any case, and the default methods' configs when
    no token is given, so that every option error comes before any work. A token naming
    an existing folder is the image folder swallowed by ``--methods M [M ...]``.
    """
    items = [tokens] if isinstance(tokens, str) else list(tokens or ())
    toks = [t.strip() for m in items for t in str(m).split(",") if t.strip()]
    for t in toks:
        if Path(t).is_dir():
            raise InputFileError(f"--methods got the folder {t!r}: put IMAGE_DIR before --methods "
                                 f"(run.py {t} --methods irls sdp) or separate the methods by commas")
    check_sections(yaml_data)
    if not toks:
        for m in _REGISTRY.values():
            if m.default is not None:
                method_config_from(m.name, yaml_data, None, (overrides or {}).get(m.name))
    specs: dict[str, MethodSpec] = {}
    for t in toks:
        spec = parse_method(t, yaml_data, overrides)
        specs.setdefault(spec.label, spec)
    return list(specs.values())


def default_methods(vg: ViewGraph, run_config: Any = None, yaml_data: Mapping[str, Any] | None = None,
                    overrides: Overrides | None = None) -> tuple[list[MethodSpec], list[str]]:
    """The methods ``run.py`` runs without ``--methods``, and notes on the defaults it skipped."""
    specs, notes = [], []
    for m in _REGISTRY.values():
        decision = m.default(vg, run_config) if m.default is not None else False
        if decision is True:
            cfg = method_config_from(m.name, yaml_data, None, (overrides or {}).get(m.name))
            specs.append(MethodSpec(m.label(cfg), m.name, cfg))
        elif isinstance(decision, str) and decision:
            notes.append(decision)
    return specs, notes


# ----------------------------------------------------------------------- built-ins
def _sdp_default(vg: ViewGraph, run_config: Any) -> bool | str:
    max_n = int(getattr(run_config, "sdp_max_n", 60))
    if vg.H is not None and vg.n_cameras <= max_n:
        return True
    if vg.n_cameras > max_n:
        return f"SDP-cSO(3) not run by default: N={vg.n_cameras} > run.sdp_max_n={max_n}"
    return False


register(Method("irls", IRLSConfig, irls, default=lambda vg, run: True, token_option="loss", error_vs_time=True,
                help="robust IRLS of paper 1 (Algorithm 3) with a loss of Table 1, ℓ½ by default"))
register(Method("irls-h", IRLSHConfig, irls_h, needs_H=True, default=lambda vg, run: vg.H is not None,
                token_option="loss",
                help="IRLS with each residual in its two-view H metric, calibrated per edge (needs H)"))
register(Method("l1", L1Config, solve_l1, help="paper 1, Algorithm 2 alone (ℓ1 steps to convergence)"))
register(Method("weiszfeld", WeiszfeldConfig, weiszfeld, help="Hartley et al. (2011), one camera at a time"))
register(Method("sdp", SdpConfig, solve_sdp, needs_H=lambda cfg: VARIANTS[cfg.variant][0], default=_sdp_default,
                token_option="variant", section="sdp", takes_init=False,
                help="paper 2's certifiable SDP on the robust stage's edges (cso3 needs H; cso3-iso, o3-iso do not)"))
register(Method("colmap-ra", ColmapRAConfig, colmap_ra, takes_init=False,
                default=lambda vg, run: True if have_pycolmap() else "colmap-ra not run: pycolmap is not installed",
                help="COLMAP's rotation averaging (pycolmap) on our view graph, for comparison"))
