"""Scoring models against recordings (`soma eval`, `soma bench accuracy`); the per-frame
metrics and how they are masked are :mod:`soma_ros.core.scoring`.

* :mod:`.baselines` -- the trained model and the baselines rolled out beside it;
* :mod:`.evaluate` -- open-loop rollouts of a dataset split and the report;
* :mod:`.ground_truth` -- the reference world's object points (evaluation only);
* :mod:`.viz` -- contact sheets and videos;
* :mod:`.accuracy` -- the accuracy table over objects and baselines.
"""
