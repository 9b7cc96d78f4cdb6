"""soma_ros trainer: bag ingestion, scene set-up, training, evaluation and the
discrepancy workflow. Pure Python + torch; never needs a running ROS graph."""
