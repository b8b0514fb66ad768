"""Evaluation runner: estimators × recordings -> metrics, JSON/Markdown tables, plots, TUM files.

For every recording and every estimator:

1. the estimator runs on the recording (``est.run(seq, init_quat, init_index)``, or once on all
   recordings with ``est.run_batch(seqs, init_quats, init_indices)`` when it has that method);
   an estimator with ``axes == 6`` gets the recording without magnetometer and is scored as
   6-axis; ``init_index`` is the first sample with valid ground truth and ``init_quat`` its
   ground-truth attitude (:func:`tcn_ahrs.estimators.base.initial_state`; what each estimator
   does with them: :class:`~tcn_ahrs.estimators.base.Estimator`). The difference this leaves at the first
   scored sample is removed for AAE/AYE by their alignment (:mod:`tcn_ahrs.metrics`); BROAD's
   errors are never aligned (BROAD trials start with a rest phase whose ground truth is valid);
2. the metrics of :func:`tcn_ahrs.metrics.sequence_metrics` are computed on ``seq.scored()``;
   ``inclination_deg`` (BROAD's inclination error, needs no heading) for every recording; an
   estimator with ``heading_free = True`` (RIANN) gets ``null`` AAE/AYE/total/heading
   (inclination only);
3. optionally a plot (roll/pitch/yaw vs ground truth, error over time, ``gyro_correction`` if the
   estimator reports it — the paper's Figs. 3-8) and TUM trajectories for ``evo`` are written.

The results are one plain dict, exactly what is written to ``results.json``::

    {"dataset": str, "align": bool, "recordings": [names...],
     "methods": {method: {"recordings": [{"name", "n_samples", "duration_s", "axes",
                                          "n_scored", "aae_deg", "aye_deg",
                                          ["total_deg", "heading_deg", "inclination_deg",
                                           "broad_mode"], "run_time_s"}, ...],
                          "mean": {metric: mean over recordings with scored samples},
                          "groups": {group: {"n_recordings": k, metric: mean}}}}}

NaN (a diverged estimator) is stored as ``null``. Groups come from ``seq.meta["groups"]``
(BROAD: ``undisturbed``, ``disturbed``, ``tapping``, ...).

Output layout under ``out_dir``::

    results.json  results.md
    plots/<method>/<recording>.png
    trajectories/<method>/<recording>.txt       (TUM: t x y z qx qy qz qw, positions 0)
    trajectories/groundtruth/<recording>.txt    (valid ground-truth samples only)
"""
from .files import plot_recording, safe_name, write_tum
from .reports import (label, average_rows, averages_markdown, compare_markdown, group_table,
                      markdown_table, print_table, results_markdown)
from .runner import evaluate, load_results

__all__ = ["evaluate", "load_results", "markdown_table", "group_table", "results_markdown", "print_table",
           "compare_markdown", "averages_markdown", "average_rows", "write_tum", "plot_recording", "safe_name",
           "label"]
