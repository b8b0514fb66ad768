"""The experiments: compositions of the one evaluation runner that answer a question and write a
JSON and a markdown table.

* :mod:`.compare` (with :mod:`.columns`, which method each column is): methods side by side on one
  dataset, tuned on its training recordings (``tcn-ahrs compare``);
* :mod:`.crossval`: nested leave-recordings-out folds of the learned model (``tcn-ahrs crossval``);
* :mod:`.search`: the best estimator family for a device, nested folds (``tcn-ahrs search``);
* :mod:`.transfer`: every checkpoint on every dataset, and the rate sweep (``benchmark transfer``);
* :mod:`.lodo`: leave one dataset out (``benchmark lodo``);
* :mod:`.finetune`: fine-tuning on a few recordings of a device never seen (``benchmark finetune``).
"""
