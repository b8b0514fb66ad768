"""The one registry of attitude estimators: method name -> how to build it.

Every estimator that ``train``'s final table, ``evaluate``, ``compare``, ``benchmark`` and
``crossval`` can run is registered here by the module that defines it, with the decorator
:func:`register`::

    @register("mahony", kind="classical")          # a ClassicalEstimator subclass
    @dataclass
    class Mahony(ClassicalEstimator): ...

=============  ==================================================================================
kind           what ``build(name, axes, **params)`` returns
=============  ==================================================================================
``raw``        :class:`~tcn_ahrs.estimators.raw.RawIntegration` (column ``Raw IMU``)
``classical``  a :class:`~tcn_ahrs.estimators.classical.ClassicalEstimator` subclass (batched
               torch filter; tuned over ``grid`` in one batched call per chunk)
``peer``       a PyPI peer wrapper (:mod:`tcn_ahrs.estimators.peers`; raises
               :class:`~tcn_ahrs.estimators.peers.PeerUnavailable` when its library is missing)
``learned``    a checkpoint (:class:`~tcn_ahrs.estimators.learned.LearnedEstimator`, ``ckpt=``)
``recorded``   an attitude the device recorded beside the IMU (:mod:`tcn_ahrs.estimators.recorded`:
               the phone OS's own, ``phone_os``), read from the recording's file
=============  ==================================================================================

Column names: ``<method><axes>d`` (``ecf9d`` uses the magnetometer, ``ecf6d`` does not),
``Raw IMU``, or the label given to :func:`build`.

Adding a method is one file: a module that registers its class, either inside this package
(every module here is imported on first use) or anywhere importable and listed in the configs'
``plugins`` (``plugins=[my_package.my_filter]``; :func:`load_plugins` imports it).
"""
from __future__ import annotations

import importlib
import itertools
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

KINDS = ("raw", "classical", "peer", "learned", "recorded")


@dataclass(frozen=True)
class Method:
    """One registered method.

    name:    registry name (``"ecf"``, ``"vqf"``, ``"ahrs_madgwick"``).
    kind:    one of :data:`KINDS`.
    factory: ``factory(axes=..., **params)`` -> estimator (``learned``: ``factory(ckpt=..., ...)``).
    axes:    the axes it runs at (``(6,)`` for a 6-axis-only method such as RIANN).
    grid:    tuning grid, a list of keyword-argument dicts (empty: not tunable).
    """

    name: str
    kind: str
    factory: Callable[..., Any]
    axes: Tuple[int, ...] = (6, 9)
    grid: Tuple[Dict[str, Any], ...] = ()

    @property
    def tunable(self) -> bool:
        return len(self.grid) > 0


_METHODS: Dict[str, Method] = {}
_loaded = False


def register(name: str, kind: str, axes: Sequence[int] = (6, 9), grid: Optional[Sequence[Dict[str, Any]]] = None):
    """Class (or factory) decorator registering ``name``. ``grid`` defaults to the grid
    combinations of a classical class's ``default_grid``. Registering a name twice with a
    different factory is an error (two modules claiming one column)."""
    if kind not in KINDS:
        raise ValueError(f"register({name!r}): kind must be one of {KINDS}, got {kind!r}")
    bad = [a for a in axes if a not in (6, 9)]
    if bad or not axes:
        raise ValueError(f"register({name!r}): axes must be a non-empty subset of (6, 9), got {tuple(axes)}")

    def deco(factory):
        g = grid
        if g is None and kind == "classical":
            g = grid_combinations(factory.default_grid) if getattr(factory, "default_grid", None) else []
        m = Method(name, kind, factory, tuple(int(a) for a in axes), tuple(dict(p) for p in (g or [])))
        old = _METHODS.get(name)
        if old is not None and old.factory is not factory and _qualname(old.factory) != _qualname(factory):
            raise ValueError(f"method {name!r} is registered twice ({_qualname(old.factory)} and {_qualname(factory)})")
        _METHODS[name] = m
        if kind == "classical":
            factory.method = name
        return factory

    return deco


def grid_combinations(grid: Mapping[str, Sequence]) -> List[Dict[str, float]]:
    """Cartesian product of ``grid`` (name -> values) as a list of dicts (first key slowest)."""
    keys = list(grid)
    for k in keys:
        if len(grid[k]) == 0:
            raise ValueError(f"grid entry {k!r} is empty")
    return [dict(zip(keys, vals)) for vals in itertools.product(*(grid[k] for k in keys))]


def _qualname(f) -> str:
    return f"{getattr(f, '__module__', '?')}.{getattr(f, '__qualname__', repr(f))}"


def _load_builtin() -> None:
    """Import every module of this package once (each registers its methods): a new estimator
    module dropped into ``tcn_ahrs/estimators/`` is found without editing anything."""
    global _loaded
    if not _loaded:
        _loaded = True
        import pkgutil

        from . import __path__ as here

        for info in sorted(pkgutil.iter_modules(here), key=lambda i: i.name):
            if info.name not in ("base", "registry"):
                importlib.import_module(f"{__package__}.{info.name}")


def load_plugins(modules: Optional[Sequence[str]]) -> None:
    """Import the modules that register further methods (the configs' ``plugins`` list)."""
    for mod in modules or []:
        try:
            importlib.import_module(str(mod))
        except ImportError as e:
            raise ValueError(f"plugins: cannot import {mod!r} ({e}); expected an importable module "
                             "that registers estimators with tcn_ahrs.estimators.registry.register") from None


def methods(kind: Optional[str] = None) -> Tuple[str, ...]:
    """Registered method names (of one ``kind``), raw first, then classical, peer, learned, each
    in registration order."""
    _load_builtin()
    kinds = KINDS if kind is None else (kind,)
    return tuple(n for k in kinds for n, m in _METHODS.items() if m.kind == k)


def get(name: str) -> Method:
    _load_builtin()
    if name not in _METHODS:
        raise ValueError(f"unknown method {name!r}; expected one of {list(methods())} "
                         "(or a module in plugins= that registers it)")
    return _METHODS[name]


def build(name: str, axes: Optional[int] = None, label: Optional[str] = None, **params):
    """The estimator of method ``name`` at ``axes`` (None: the method's first) with keyword
    ``params``; ``label`` renames its column."""
    m = get(name)
    if m.kind == "learned":
        return m.factory(name=label or "Learned", **params)
    ax = m.axes[-1] if axes is None else int(axes)
    if ax not in m.axes:
        raise ValueError(f"method {name!r} runs at axes {m.axes}, not {ax}")
    est = m.factory(axes=ax, **params)
    if label is not None:
        if hasattr(type(est), "label"):
            est.label = label
        else:
            est.name = label
    return est


def check_method_names(names: Optional[Sequence[str]]) -> None:
    """ValueError for a name that is no registered method (``vqf``) nor column (``vqf6d``),
    naming the nearest: a misspelt baseline must not be skipped silently."""
    import difflib

    known = list(methods())
    for n in names or []:
        n = str(n)
        if n in known or (n[-2:] in ("6d", "9d") and n[:-2] in known):
            continue
        near = difflib.get_close_matches(n, known, n=1)
        raise ValueError(f"baselines: unknown method {n!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
                         + f"; expected one of {sorted(known)} (or a column name such as 'vqf6d')")


def baseline_estimators(names: Optional[Sequence[str]], axes: int = 9) -> List[Any]:
    """Baselines by name for ``train``'s and ``evaluate``'s tables: method names (``raw``,
    ``ecf``, ``vqf``, ...) at the data's ``axes`` (or the method's own when it runs only at
    others), or column names (``vqf6d``). Unavailable or unknown ones are skipped with a
    warning (a missing baseline must not lose a trained model's evaluation)."""
    check_method_names(names)
    out = []
    for n in names or []:
        n = str(n)
        try:
            ax = int(axes)
            if n not in methods() and n[-2:] in ("6d", "9d") and n[:-2] in methods():
                n, ax = n[:-2], int(n[-2])
            m = get(n)
            if m.kind == "learned":
                raise ValueError("learned models are given as checkpoints, not as baselines")
            out.append(build(n, ax if ax in m.axes else m.axes[0]))
        except Exception as e:  # noqa: BLE001
            warnings.warn(f"baseline {n!r} unavailable, skipped: {type(e).__name__}: {e}")
    return out
