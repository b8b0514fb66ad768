"""Checks of user-given values: one message format (the key, what was expected, what was given)."""
from __future__ import annotations

from typing import Any, Optional


def check_number(value: Any, key: str, kind=float, low: Optional[float] = None, low_ok: bool = True,
                 high: Optional[float] = None):
    """``value`` as ``kind`` within [low (or > low), high); a ``ValueError`` naming ``key`` otherwise."""
    rng = []
    if low is not None:
        rng.append(f"{'>=' if low_ok else '>'} {low:g}")
    if high is not None:
        rng.append(f"< {high:g}")
    want = f"{'an integer' if kind is int else 'a number'}{' ' + ' and '.join(rng) if rng else ''}"
    try:
        if isinstance(value, bool) or value is None:
            raise TypeError
        v = kind(value)
        if kind is int and float(value) != v:
            raise TypeError
    except (TypeError, ValueError):
        raise ValueError(f"{key}: expected {want}, got {value!r}") from None
    if (low is not None and (v < low or (v == low and not low_ok))) or (high is not None and v >= high):
        shown = value.item() if hasattr(value, "item") else value  # 3.5, not np.float64(3.5)
        raise ValueError(f"{key}: expected {want}, got {shown!r}")
    return v


def set_threads(value: Any) -> None:
    """``threads=N``: torch's CPU threads (None: torch's default); an integer >= 1."""
    if value is None:
        return
    import torch

    torch.set_num_threads(check_number(value, "threads", int, 1))
