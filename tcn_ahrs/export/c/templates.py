"""The C templates shipped beside these modules and the literal writers the generated files use
(read by the backbone's runtime, :mod:`.runtime`, and the tuned ECF's, :mod:`.classical`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

TEMPLATES = Path(__file__).resolve().parent  # model.h.in, model.c.in, helpers.h.in (package data)


def template(name: str) -> str:
    """A C template shipped beside this module; a source template (``*.c.in``) gets the REAL
    helpers and the input contract (``helpers.h.in``, ``contract.c.in``) written in."""
    text = (TEMPLATES / name).read_text()
    if not name.endswith(".c.in"):
        return text
    return (text.replace("@HELPERS@", (TEMPLATES / "helpers.h.in").read_text())
            .replace("@CONTRACT@", (TEMPLATES / "contract.c.in").read_text()))


def _f32(a) -> str:
    """float32 values as exact C literals."""
    a = np.asarray(a, dtype=np.float32).reshape(-1)
    def lit(v: float) -> str:
        t = f"{v:.9g}"
        return (t if any(ch in t for ch in ".e") else t + ".0") + "f"  # 0 -> 0.0f, not 0f
    return ",\n".join(", ".join(lit(float(v)) for v in a[i:i + 8]) for i in range(0, a.size, 8)) or "0.0f"


def _f64(a) -> str:
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    return ",\n".join(", ".join(repr(float(v)) for v in a[i:i + 6]) for i in range(0, a.size, 6)) or "0.0"
