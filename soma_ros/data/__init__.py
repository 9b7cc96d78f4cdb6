"""Bag ingestion: recorded episodes (rosbag2, sqlite3 or mcap) as synchronised arrays and
as training tensors.

* :mod:`.bags` -- a bag -> :class:`~.bags.Episode` (cameras, images, masks, depth, joint
  states, TF), with one-line :class:`~.bags.BagError` s.
* :mod:`.dataset` -- a dataset folder -> episode references, and an episode ->
  :class:`~.dataset.EpisodeData` (per-frame cameras and robot actions in the sim frame).
"""
