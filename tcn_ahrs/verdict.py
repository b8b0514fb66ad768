"""The project's promise — never worse than the best classical filter — as one rule, used by every
place that says it: the transfer matrix (:mod:`tcn_ahrs.experiments.transfer`), the family search's
rows (:mod:`tcn_ahrs.experiments.search`), fine-tuning's adoption
(:mod:`tcn_ahrs.training.adaptation`) and the tables' scripts (scripts/nested_table.py).

A candidate is never worse than a reference when its mean AAE and its mean inclination are no
higher, compared at the tables' resolution (0.01°: a difference no reader of a table can see is a
tie). It is better when, in addition, its AAE is lower at that resolution. Scores in degrees;
a non-finite candidate (a diverged filter) is never "never worse".
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional


@dataclass(frozen=True)
class VerdictConfig:
    """The rule's one margin, once."""

    resolution_deg: float = 0.01  # °: scores compared rounded to this (the tables' rounding)


VERDICT = VerdictConfig()


def _at(x: float, cfg: VerdictConfig) -> float:
    return round(float(x) / cfg.resolution_deg)


def never_worse(aae: Optional[float], incl: Optional[float], ref_aae: Optional[float], ref_incl: Optional[float],
                cfg: VerdictConfig = VERDICT) -> bool:
    """AAE and inclination no higher than the reference's at ``cfg.resolution_deg``; a reference
    without an inclination (None) is judged on the AAE alone; no candidate or reference AAE: False."""
    if aae is None or ref_aae is None or not math.isfinite(aae):
        return False
    if _at(aae, cfg) > _at(ref_aae, cfg):
        return False
    if ref_incl is None:
        return True
    return incl is not None and math.isfinite(incl) and _at(incl, cfg) <= _at(ref_incl, cfg)


def never_worse_means(means: Optional[Mapping[str, Any]], ref: Optional[Mapping[str, Any]],
                      cfg: VerdictConfig = VERDICT) -> bool:
    """:func:`never_worse` on two rows of a results table ({"aae_deg", "inclination_deg"}); False
    where either row is missing."""
    if not means or not ref:
        return False
    return never_worse(means.get("aae_deg"), means.get("inclination_deg"), ref.get("aae_deg"),
                       ref.get("inclination_deg"), cfg)


def better(aae: Optional[float], incl: Optional[float], ref_aae: Optional[float], ref_incl: Optional[float],
           cfg: VerdictConfig = VERDICT) -> bool:
    """Never worse, and a lower AAE at ``cfg.resolution_deg``: what replacing the reference needs."""
    return never_worse(aae, incl, ref_aae, ref_incl, cfg) and _at(aae, cfg) < _at(ref_aae, cfg)
