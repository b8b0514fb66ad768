"""The search's compute budget (``search.budget_minutes``) and its one progress bar."""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from typing import Iterator, List, Optional

CLASSICAL_SHARE = 0.3
"""Part of the budget set aside for the classical candidates until one fold has measured them."""


class Budget:
    """What the search may still spend: each training gets an equal share of the budget left once
    the classical work still to come is set aside (estimated from the folds done so far, else
    :data:`CLASSICAL_SHARE` of the budget). ``minutes`` None: no cap."""

    def __init__(self, minutes: Optional[float], n_trainings: int, n_folds: int):
        self.minutes = None if minutes is None else float(minutes)
        self.trainings_left, self.folds_left = int(n_trainings), int(n_folds)
        self.t0 = time.perf_counter()
        self._fold_t0, self._fold_training = self.t0, 0.0
        self.classical_per_fold: List[float] = []  # minutes

    def spent(self) -> float:
        return (time.perf_counter() - self.t0) / 60.0

    def describe(self, n_recipes: int) -> str:
        if not n_recipes:
            return "learned candidates: none (search.learn=[])"
        cap = ("no time cap (search.budget_minutes=null)" if self.minutes is None else
               f"budget {self.minutes:g} min: each training gets an equal share of what the classical candidates leave")
        return (f"learned candidates: {n_recipes} recipe(s) trained in each of {self.folds_left} outer folds "
                f"(+ the release if one wins), {self.trainings_left} trainings; {cap}")

    def _classical_left(self) -> float:
        if self.minutes is None:
            return 0.0
        if self.classical_per_fold:
            per_fold = sum(self.classical_per_fold) / len(self.classical_per_fold)
        else:
            per_fold = CLASSICAL_SHARE * self.minutes / max(1, self.folds_left)
        return per_fold * self.folds_left

    @contextmanager
    def training(self) -> Iterator[Optional[float]]:
        """The next training's time cap in minutes (None: uncapped), its time counted as training."""
        from .learn import share_minutes

        minutes = share_minutes(self.minutes, self.spent(), self.trainings_left, self._classical_left())
        t = time.perf_counter()
        try:
            yield minutes
        finally:
            self.trainings_left = max(0, self.trainings_left - 1)
            self._fold_training += (time.perf_counter() - t) / 60.0

    def fold_done(self) -> None:
        now = time.perf_counter()
        self.classical_per_fold.append(max(0.0, (now - self._fold_t0) / 60.0 - self._fold_training))
        self._fold_t0, self._fold_training = now, 0.0
        self.folds_left = max(0, self.folds_left - 1)

    def overrun(self) -> Optional[str]:
        """A sentence when the search spent more than its budget, else None."""
        if self.minutes is not None and self.spent() > self.minutes * 1.05:
            return (f"the search took {self.spent():.1f} min, over its budget of {self.minutes:g} min "
                    "(the classical candidates alone took longer than their share: fewer search.trials or a "
                    "search.tune_seconds keep it)")
        return None


class Progress:
    """One bar over the whole search (tqdm on stderr); ``write`` prints above it. Where stderr is no
    terminal (a log file, CI) the bar is a line every ``every`` of the work instead."""

    def __init__(self, total: int, what: str, every: float = 0.1):
        from tqdm import tqdm

        self.live = sys.stderr.isatty()
        self.what, self.every, self._said = what, every, 0.0
        self.bar = tqdm(total=max(1, int(total)), desc=what, file=sys.stderr, mininterval=2.0, leave=True,
                        disable=not self.live,
                        bar_format="{desc}: {percentage:3.0f}%|{bar:20}| {elapsed} elapsed, ~{remaining} left {postfix}")
        self.total, self.n, self.t0 = max(1, int(total)), 0, time.perf_counter()

    def step(self, what: str, n: int = 1) -> None:
        self.n = min(self.total, self.n + n)
        if self.live:
            self.bar.set_postfix_str(what[:60], refresh=False)
            self.bar.update(n)
            return
        done = self.n / self.total
        if done >= self._said + self.every or self.n == self.total:
            self._said = done
            spent = (time.perf_counter() - self.t0) / 60.0
            left = spent * (1.0 - done) / done if done > 0 else float("nan")
            print(f"[{self.what} {done:4.0%}: {spent:.1f} min, ~{left:.1f} min left] {what}", flush=True)

    def write(self, line: str) -> None:
        if self.live:
            self.bar.write(line, file=sys.stdout)
        else:
            print(line)
        sys.stdout.flush()

    def close(self) -> None:
        self.bar.close()
