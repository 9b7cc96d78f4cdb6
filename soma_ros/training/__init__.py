"""Offline training from rosbags (`soma train`).

* :mod:`.config` -- :class:`~.config.TrainConfig`, loaded strictly from ``config/train/*.yaml``;
* :mod:`.train` -- the loss, the two-stage schedule, validation, checkpoints and logs.
"""
