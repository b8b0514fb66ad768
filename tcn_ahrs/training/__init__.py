"""Training, in parts: the LightningModule (:mod:`.module`), the trainer assembly — callbacks and
loggers from the ``callbacks``/``logger`` config groups, resume search (:mod:`.trainer`) — and the
run's checks and data-driven starting points (:mod:`.setup`). The entry's body is
:func:`tcn_ahrs.training.run.train_main`."""
