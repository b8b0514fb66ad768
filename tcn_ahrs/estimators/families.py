"""The estimator families the search (:mod:`tcn_ahrs.experiments.search`) chooses among, each with its
knobs' ranges and defaults, the static calibrations they run on, and the one scoring of a
candidate (mean AAE and inclination with the yardstick of :mod:`tcn_ahrs.metrics`)."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .. import calibration as cal_mod
from ..filters.ecf import ECFParams
from ..filters.madgwick import MadgwickParams
from ..filters.mahony import MahonyParams
from ..kernels.backbone_layout import BackboneParams
from ..kernels.params import searched, suggest
from ..metrics import aae_and_inclination
from ..sequence import ImuSequence
from .base import initial_state


# ------------------------------------------------------------------------------ families

@dataclass(frozen=True)
class Family:
    """A classical family: ``build(axes, **knobs)`` -> estimator; its knobs, their ranges and defaults
    read from the filter's parameter dataclass ``params`` (:func:`tcn_ahrs.kernels.params.knob`:
    the fields with a search range), never restated here; ``space(trial)`` -> knobs (an Optuna
    trial); :meth:`defaults_for` is what the study tries first (enqueued), so the tuned filter starts
    from the untuned one."""

    name: str
    build: Callable[..., Any]
    params: Optional[type] = None

    @property
    def knobs(self) -> Tuple[str, ...]:
        return tuple(searched(self.params)) if self.params is not None else ()

    def space(self, trial) -> Dict[str, float]:
        return suggest(trial, self.params) if self.params is not None else {}

    def defaults_for(self, axes: int) -> Dict[str, float]:
        """The knobs at the filter's own defaults (what it runs without arguments) for ``axes``."""
        if self.params is None:
            return {}
        own = {f.name: f.default for f in fields(self.params)}
        if self.params is MadgwickParams:  # ahrs's default depends on the axes
            own["beta"] = MadgwickParams.default_beta(axes)
        return {k: float(own[k]) for k in self.knobs}


def _raw(axes: int, **_):
    from .raw import RawIntegration
    return RawIntegration(axes=6)


def _classical(method: str):
    def build(axes: int, **knobs):
        from . import registry
        return registry.build(method, axes, **knobs)
    return build


def _backbone(axes: int, **knobs):
    from .backbone import Backbone
    own = {"tau_acc", "tau_mag", "motion_bias", "rest_bias", "bias_clip", "mag_rejection"}
    return Backbone(axes=axes, **{k: v for k, v in knobs.items() if k in own},
                    extra={k: v for k, v in knobs.items() if k not in own} or None)


FAMILIES: Dict[str, Family] = {f.name: f for f in [
    Family("strapdown", _raw),
    Family("ecf", _classical("ecf"), ECFParams),
    Family("mahony", _classical("mahony"), MahonyParams),
    Family("madgwick", _classical("madgwick"), MadgwickParams),
    # VQF's full parameter set: inclination and heading time constants, bias estimation (its clip,
    # sigmas, forgetting), rest detection (thresholds and times), disturbance rejection
    Family("backbone", _backbone, BackboneParams),
]}

SIMPLICITY = ("strapdown", "ecf", "mahony", "madgwick", "backbone", "residual", "closed_loop", "paper")
"""Ties go to the earlier (simpler) family."""

CALIBRATIONS: Dict[str, Optional[Dict[str, str]]] = {
    "none": None,
    "gyro_bias": {"gyro": "bias", "acc": "none", "mag": "none"},
    "full": {"gyro": "full", "acc": "bias", "mag": "full"},
    "device_check": {},
}
"""Calibrations a classical candidate runs on: static ones fitted on the training recordings
(:func:`tcn_ahrs.calibration.fit_calibration`'s modes), or ``device_check`` — each recording's own
gyro bias at rest, read when it runs (:class:`tcn_ahrs.device_check.RestBiasCalibration`)."""


def fit_named_calibration(name: str, train: Sequence[ImuSequence]):
    """The calibration ``name`` of :data:`CALIBRATIONS` for recordings like ``train`` (None: raw)."""
    if name not in CALIBRATIONS:
        raise ValueError(f"calibration: unknown {name!r}; expected one of {list(CALIBRATIONS)}")
    if name == "device_check":
        from ..device_check import RestBiasCalibration
        return RestBiasCalibration()
    return None if CALIBRATIONS[name] is None else cal_mod.fit_calibration(train, strict=False, **CALIBRATIONS[name])


def calibration_from_dict(d: Optional[Dict[str, Any]]):
    """The calibration an estimator file holds (:func:`save_estimator`), None for raw signals."""
    if d is None:
        return None
    if d.get("kind") == "device_check":
        from ..device_check import RestBiasCalibration
        return RestBiasCalibration()
    return cal_mod.StaticCalibration.from_dict(d)


class Calibrated:
    """An estimator run on statically calibrated signals; name ``"<name> +cal"`` unless given."""

    def __init__(self, inner, cal: Optional[cal_mod.StaticCalibration], name: Optional[str] = None):
        self.inner, self.cal = inner, cal
        self.name = name or (inner.name if cal is None else f"{inner.name} +cal")
        self.axes = getattr(inner, "axes", None)
        self.heading_free = bool(getattr(inner, "heading_free", False))
        self.ckpt_path = getattr(inner, "ckpt_path", None)  # a learned inner's checkpoint (the search's records)

    def run(self, seq: ImuSequence, init_quat=None, init_index: int = 0):
        return self.inner.run(seq if self.cal is None else self.cal.apply(seq), init_quat, init_index)


def recording_scores(est, seqs: Sequence[ImuSequence], axes: int) -> Tuple[List[float], List[float]]:
    """(AAE per recording, inclination per recording) of ``est`` over ``seqs`` with the one
    yardstick; every entry inf if it diverges anywhere."""
    aae, incl = [], []
    for s in seqs:
        view = s.without_mag() if (axes == 6 and s.has_mag) else s
        k0, q0 = initial_state(s)
        try:
            q = est.run(view, q0, k0).quat
        except (FloatingPointError, ZeroDivisionError, np.linalg.LinAlgError):
            # a knob point the filter cannot run with numerically (e.g. the backbone's numba kernel
            # dividing by zero on OxIOD at tau_acc 1.06 s, rest_th_acc 0.2): scored as diverged, never
            # chosen. Any other error (a refusal, a bug: a ValueError was scored as "diverged" and the
            # candidate silently dropped) is raised with the candidate and recording named
            return [math.inf] * len(seqs), [math.inf] * len(seqs)
        except ValueError as e:
            raise ValueError(f"{getattr(est, 'name', est)} on {s.name}: {e}") from e
        if not np.all(np.isfinite(q)):
            return [math.inf] * len(seqs), [math.inf] * len(seqs)
        a, i = aae_and_inclination(s, q, view.num_axes)
        aae.append(float(a))
        incl.append(float(i))
    return aae, incl


def mean_scores(est, seqs: Sequence[ImuSequence], axes: int) -> Tuple[float, float]:
    """(mean AAE, mean inclination) of ``est`` over ``seqs`` (:func:`recording_scores`); inf if it
    diverges anywhere."""
    aae, incl = recording_scores(est, seqs, axes)
    return float(np.mean(aae)), float(np.mean(incl))


# ------------------------------------------------------------------------------ the released file

ESTIMATOR_FORMAT = "tcn-ahrs classical estimator v1"


def save_estimator(path, family: str, axes: int, knobs: Dict[str, float],
                   cal: Optional[cal_mod.StaticCalibration], provenance: Optional[Dict[str, Any]] = None) -> None:
    """A chosen classical candidate as a JSON file that ``tcn-ahrs evaluate ckpt=FILE`` runs:
    family, axes, knobs, the static calibration's constants. Written atomically (a temporary
    file renamed over the target): a killed write never leaves half a file."""
    import json
    import os
    from pathlib import Path

    if family not in FAMILIES:
        raise ValueError(f"save_estimator: family {family!r} is not a classical family ({list(FAMILIES)})")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    doc = {"format": ESTIMATOR_FORMAT, "family": family, "axes": int(axes), "knobs": dict(knobs),
           "calibration": None if cal is None else cal.to_dict(), "provenance": dict(provenance or {})}
    tmp = p.with_name(p.name + ".partial")
    tmp.write_text(json.dumps(doc, indent=1, default=float))
    os.replace(tmp, p)


def is_estimator_file(path) -> bool:
    return str(path).endswith(".json")


def read_estimator(path) -> Dict[str, Any]:
    """The checked contents of a file written by :func:`save_estimator` (family, axes, knobs,
    calibration, provenance); ValueError naming the file and the field when it is not one."""
    import json
    from pathlib import Path

    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: no such estimator file (written by tcn-ahrs search)") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{p}: not JSON ({e}); expected an estimator file written by tcn-ahrs search") from None
    if not isinstance(doc, dict) or doc.get("format") != ESTIMATOR_FORMAT:
        raise ValueError(f"{p}: field 'format': expected {ESTIMATOR_FORMAT!r}, got {doc.get('format') if isinstance(doc, dict) else doc!r}")
    if doc.get("family") not in FAMILIES:
        raise ValueError(f"{p}: field 'family': expected one of {list(FAMILIES)}, got {doc.get('family')!r}")
    if doc.get("axes") not in (6, 9):
        raise ValueError(f"{p}: field 'axes': expected 6 or 9, got {doc.get('axes')!r}")
    return doc


def load_estimator(path, name: Optional[str] = None) -> Calibrated:
    """The estimator of a file written by :func:`save_estimator` (checked by :func:`read_estimator`)."""
    from pathlib import Path

    p = Path(path)
    doc = read_estimator(p)
    fam = doc["family"]
    cal = calibration_from_dict(doc.get("calibration"))
    est = FAMILIES[fam].build(int(doc["axes"]), **dict(doc.get("knobs") or {}))
    return Calibrated(est, cal, name=name or f"{fam} ({p.stem})")
