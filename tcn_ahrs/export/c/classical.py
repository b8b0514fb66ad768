"""The C runtime of a classical estimator file (``tcn-ahrs search``'s JSON: family, axes, knobs,
static calibration) for the families with a C kernel: the ECF (``ecf.c.in``: the per-sample
weights of Eqs. 5-8 and the step of Eq. 4 translated from :mod:`tcn_ahrs.kernels.classical`, the
quaternion kernels from :mod:`tcn_ahrs.kernels.quat`; the knobs and the calibration written in).
The same API as the residual models' runtime (``name_reset``, ``name_step``, ``name_run``), so
:class:`~tcn_ahrs.export.c.runtime.CRuntime` and ``examples/c/`` run either."""
from __future__ import annotations

import re
from dataclasses import fields
from typing import Any, Dict

import numpy as np

from ...conventions import GRAVITY, INPUT_LIMITS, MAX_DT, MIN_DT
from ...kernels import classical as KC
from ...kernels import quat as KQ
from ..inputs import ExportError
from .templates import _f64, template
from .translate import kernel_c

C_FAMILIES = ("ecf",)  # the classical families with a C runtime


def _lits(a) -> str:
    return ", ".join(f"R_({float(v)!r})" for v in np.asarray(a, dtype=np.float64).reshape(-1))


def generate_classical_c(doc: Dict[str, Any], name: str, source: str = "a tcn-ahrs search file") -> Dict[str, Any]:
    """``{"h", "c", "info"}`` of an estimator file's contents (:func:`~tcn_ahrs.estimators.families.read_estimator`);
    a family without a C runtime is an ExportError naming the ones with one."""
    from ...calibration import StaticCalibration
    from ...filters.ecf import ECFParams

    fam, axes = str(doc["family"]), int(doc["axes"])
    if fam not in C_FAMILIES:
        raise ExportError(f"C export: {source} holds the classical family {fam!r}; format=c holds the residual models "
                          f"and the classical families {list(C_FAMILIES)}")
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name or ""):
        raise ExportError(f"C export: name {name!r} is not a C identifier")
    knobs = {**ECFParams().__dict__, **dict(doc.get("knobs") or {})}
    cal = StaticCalibration.from_dict(doc["calibration"]) if doc.get("calibration") else StaticCalibration()
    inv = np.linalg.inv
    kern = [kernel_c(KC, f"{name}_k_", ("ecf_weights", "ecf_step"), plain=True)[0],
            kernel_c(KQ, f"{name}_k_", ("matrix_to_quat", "qmul") + (("qrot",) if axes == 9 else ()), plain=True)[0]]
    subst = {
        "NAME": name, "UP": name.upper(), "C": str(axes), "SOURCE": source.replace("*/", "* /"),
        "KERNELS": "\n".join(kern), "USE_MAG": "1" if axes == 9 else "0",
        # every ECFParams field as @K_NORM@, @A_MIN@, ... (the template names them all)
        **{f.name.upper(): repr(float(knobs[f.name])) for f in fields(ECFParams)}, "GRAVITY": repr(float(GRAVITY)),
        "GYRO_INV": _lits(inv(cal.gyro_matrix)), "ACC_INV": _lits(inv(cal.acc_matrix)),
        "MAG_INV": _lits(inv(cal.mag_matrix)), "GYRO_BIAS": _lits(cal.gyro_bias), "ACC_BIAS": _lits(cal.acc_bias),
        "HARD_IRON": _lits(cal.hard_iron), "LIMITS": _f64(INPUT_LIMITS[:axes]), "MAX_DT": repr(float(MAX_DT)), "MIN_DT": repr(float(MIN_DT)),
    }

    def fill(text: str) -> str:
        return re.sub(r"@(\w+)@", lambda mm: subst[mm.group(1)], text)

    info = {"axes": axes, "family": fam, "knobs": {k: float(v) for k, v in knobs.items()},
            "weights_float32": 0, "ring_floats": 0, "layers": [], "weight_bytes": 0, "live_networks": [],
            "flops_per_sample": 0}
    return {"h": fill(template("ecf.h.in")), "c": fill(template("ecf.c.in")), "info": info}
