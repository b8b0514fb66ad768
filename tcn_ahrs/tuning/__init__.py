"""Choosing knobs on recordings with ground truth, never on the reported ones.

* :mod:`.grid`: the classical filters' parameters, all recordings x all grid points in one batched
  filter call (``tune_method``);
* :mod:`.knobs`: a learned model's knobs — the backbone's before training, its bias state's start,
  the residual model's inference knobs after it.
"""
