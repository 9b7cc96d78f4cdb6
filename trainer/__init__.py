"""soma_ros trainer: bag ingestion, scene set-up, training, evaluation and the
discrepancy workflow. Pure Python + torch; never needs a running ROS graph.

Pipeline (issue #5)::

    soma world --object rope --preset tiny --episodes 8 --task lift --out DATA   # or a real rig's bags
    soma reconstruct --bag DATA/rope_000 --config tiny --out SCENE               # optional: G_0 + bundle
    soma train --data DATA --config tiny --out RUN [--scene SCENE]               # -> RUN/checkpoint.pt, RUN/scene
    torchrun --nproc_per_node 2 -m soma_ros.cli train --data DATA --config tiny --out RUN2
    soma reconstruct --capture shared/data/real_rope_4view --holdout-view 3 --out CAP

Modules (owned by the trainer):

* :mod:`trainer.bags` -- rosbag2 (sqlite3 / mcap) -> synchronised arrays, one-line
  :class:`~trainer.bags.BagError` s; never reads ``/world/object_points``.
* :mod:`trainer.dataset` -- the shared episode API: :func:`~trainer.dataset.load_dataset`,
  :func:`~trainer.dataset.prepare_episode` -> :class:`~trainer.dataset.EpisodeData`
  (per-frame cameras, images, masks, depth, robot actions in the sim frame).
* :mod:`trainer.scene_setup` -- G_0 from fused masked depth + photometric refinement,
  table plane and gravity, hierarchy, scene bundle; per-episode alignment of G_0.
* :mod:`trainer.capture`, :mod:`trainer.reconstruct` -- multi-view capture folders
  and `soma reconstruct`.
* :mod:`trainer.config` -- :class:`~trainer.config.TrainConfig` (``config/train/*.yaml``).
* :mod:`trainer.train` -- `soma train`: the loss, the two-stage schedule, DDP,
  resumable checkpoints, logs.
"""
