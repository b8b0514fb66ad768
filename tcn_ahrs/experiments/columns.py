"""The columns of a comparison: which (method, axes, parameter variant) or checkpoint each
table column is, and building its estimator from the one registry.

A column is a :class:`MethodSpec` before it is built: ``vqf9d`` (a registered method on 9 axes
with its default parameters), ``vqf9d (tuned)`` (parameters filled in by
:func:`tcn_ahrs.experiments.compare.tune_methods`), ``Raw IMU``, or a checkpoint label.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from ..estimators import registry


VARIANTS = ("default", "tuned")
TUNED_SUFFIX = " (tuned)"


def default_methods(peers: bool = False) -> List[str]:
    """Every registered raw and classical method (and, with ``peers``, every peer)."""
    kinds = ("raw", "classical") + (("peer",) if peers else ())
    return [m for k in kinds for m in registry.methods(k)]


@dataclass
class MethodSpec:
    """One column of the comparison before it is built.

    name: column label (``"vqf9d"``, ``"vqf9d (tuned)"``, a checkpoint label);
    method: registry name (``"vqf"``) or ``"learned"``; axes: 6/9 (None: raw/learned);
    variant: ``"default"`` | ``"tuned"``; params: constructor keyword arguments
    (tuned ones filled in by :func:`tune_methods`); ckpt: checkpoint path for learned ones.
    """

    name: str
    method: str
    axes: Optional[int] = None
    variant: str = "default"
    params: Dict[str, Any] = field(default_factory=dict)
    ckpt: Optional[str] = None

    @property
    def kind(self) -> str:
        return registry.get(self.method).kind


def method_specs(methods: Sequence[str], data_axes: int = 9, both_axes: bool = True,
                 variants: Sequence[str] = ("default",), ckpts: Optional[Mapping[str, str]] = None) -> List[MethodSpec]:
    """The columns to compare, in order: for each method, each axes variant (9D first), each
    parameter variant (``tuned`` only for methods with a grid); then the checkpoints.

    Raises ``ValueError`` for an unknown method name or variant.
    """
    data_axes = int(data_axes)
    if data_axes not in (6, 9):
        raise ValueError(f"data.axes: expected 6 or 9, got {data_axes!r}")
    known = [m for m in registry.methods() if registry.get(m).kind != "learned"]
    bad = [m for m in methods if m not in known]
    if bad:
        raise ValueError(f"methods: unknown method(s) {bad}; expected names among {known} "
                         "(learned models go in ckpts={label: path}; more methods: plugins=[module])")
    badv = [v for v in variants if v not in VARIANTS]
    if badv or not variants:
        raise ValueError(f"variants: expected a non-empty subset of {list(VARIANTS)}, got {list(variants)}")
    axes_list = [9, 6] if (data_axes == 9 and both_axes) else [data_axes]
    specs: List[MethodSpec] = []
    for m in dict.fromkeys(methods):
        entry = registry.get(m)
        if entry.kind == "raw":
            specs.append(MethodSpec("Raw IMU", m))
            continue
        for ax in axes_list:
            if ax not in entry.axes:
                continue
            for v in variants:
                if v == "tuned" and not entry.tunable:
                    continue
                specs.append(MethodSpec(f"{m}{ax}d" + (TUNED_SUFFIX if v == "tuned" else ""), m, ax, v))
    for label, path in (ckpts or {}).items():
        specs.append(MethodSpec(str(label), "learned", ckpt=str(path)))
    names = [s.name for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"duplicate column names {dup}: checkpoint labels must differ from method columns")
    return specs


def build_estimator(spec: MethodSpec, device: str = "cpu", reanchor: Optional[int] = None):
    """The estimator of one spec (raises :class:`~tcn_ahrs.estimators.peers.PeerUnavailable`
    when a peer's library is missing)."""
    kind = spec.kind
    if kind == "learned":
        return registry.build("learned", label=spec.name, ckpt=spec.ckpt, device=device, reanchor=reanchor)
    if kind == "raw":
        return registry.build(spec.method)
    params = dict(spec.params)
    if kind == "classical":
        params["device"] = device
    return registry.build(spec.method, spec.axes, label=spec.name, **params)


def build_estimators(specs: Sequence[MethodSpec], device: str = "cpu",
                     reanchor: Optional[int] = None) -> Tuple[list, List[MethodSpec]]:
    """Estimators of ``specs``; peers whose library is missing are skipped with ONE warning
    naming them. Returns ``(estimators, specs_kept)``."""
    from ..estimators.peers import INSTALL_HINT, PeerUnavailable

    out, kept, missing = [], [], []
    for s in specs:
        try:
            out.append(build_estimator(s, device, reanchor))
            kept.append(s)
        except PeerUnavailable as e:
            missing.append(f"{s.name} ({e})")
    if missing:
        warnings.warn(f"peer estimators skipped (library not installed): {'; '.join(missing)}; "
                      f"install them with: {INSTALL_HINT}", stacklevel=2)
    return out, kept
