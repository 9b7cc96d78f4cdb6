"""Initial scenes: the splats G_0, the table plane, gravity and the hierarchy that a
rollout starts from.

* :mod:`.capture` -- multi-view capture folders and the photometric splat fit;
* :mod:`.reconstruct` -- `soma reconstruct` from a capture or an episode bag;
* :mod:`.scene_setup` -- the scene bundle from an episode, and each episode's initial state.
"""
