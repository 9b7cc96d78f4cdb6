"""The package's exceptions: one base, :class:`SomaError`, and one subclass per area.

Every error the software raises on purpose is a ``SomaError``; the ``soma`` command prints
it as one line on stderr and exits with code 2 (``--debug`` shows the traceback). Each area
class also derives from the built-in exception that callers caught before (``ValueError``
for bad input, ``RuntimeError`` for a run that cannot go on), so ``except ValueError`` keeps
working.

==================  ==============================================================
SomaError           base of all of them
ConfigError         a config file or value that does not fit its dataclass
RobotError          a URDF or robot config that cannot be used
SceneError          a splat scene (.ply / .splat / inline cloud) that cannot be used
DataError           a rosbag, dataset folder or ground-truth stream that cannot be used
CheckpointError     a checkpoint or training state that cannot be read or trusted
SimulationError     a rollout that cannot go on (a state that is not physical)
WorldError          the reference world cannot make the asked episode
NodeError           a node's command-line or ROS set-up that cannot be used
==================  ==============================================================
"""

from __future__ import annotations

__all__ = [
    "SomaError",
    "ConfigError",
    "RobotError",
    "SceneError",
    "DataError",
    "CheckpointError",
    "SimulationError",
    "WorldError",
    "NodeError",
]


class SomaError(Exception):
    """Base of every error soma_ros raises on purpose."""


class ConfigError(SomaError, ValueError):
    """A config file or value that does not fit its dataclass (the message names the key)."""


class RobotError(SomaError, ValueError):
    """A URDF or robot config that cannot be used."""


class SceneError(SomaError, ValueError):
    """A splat scene that cannot be used."""


class DataError(SomaError, ValueError):
    """A rosbag, dataset folder or ground-truth stream that cannot be used."""


class CheckpointError(SomaError, ValueError):
    """A checkpoint or training state that cannot be read or trusted."""


class SimulationError(SomaError, RuntimeError):
    """A rollout that cannot go on."""


class WorldError(SomaError, RuntimeError):
    """The reference world cannot make the asked episode."""


class NodeError(SomaError, RuntimeError):
    """A node's command line or ROS set-up that cannot be used."""
