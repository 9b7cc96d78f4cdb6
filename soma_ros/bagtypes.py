"""rosbags type store with the soma_msgs interfaces registered.

No ROS installation is needed: the same ``.msg``/``.srv`` text that builds the
``soma_msgs`` package is parsed by ``rosbags.typesys.get_types_from_msg``, so
bags written by rosbags can carry soma_msgs types and any rosbag2 tool that
reads the embedded definitions (Foxglove, rosbags, ros2 bag) can decode them.
"""

from __future__ import annotations

import sys
from functools import lru_cache
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

PACKAGE = "soma_msgs"


def interface_dir() -> Path:
    """The folder holding soma_msgs' msg/ and srv/ (the checkout's or the installed share)."""
    cands = [
        Path(__file__).resolve().parents[1] / "msg_schemas",
        Path(sys.prefix) / "share" / PACKAGE,
    ]
    try:
        from ament_index_python.packages import get_package_share_directory  # type: ignore

        cands.append(Path(get_package_share_directory(PACKAGE)))
    except Exception:
        pass
    for c in cands:
        if (c / "msg").is_dir():
            return c
    raise FileNotFoundError(f"soma_msgs interface files not found (looked in {', '.join(map(str, cands))})")


def soma_type_definitions() -> dict:
    """{type name: parsed definition} for every soma_msgs message.

    Services (srv/) are not registered: rosbags' type system models messages
    only, and rosbag2 records service traffic through service_msgs events.
    """
    root = interface_dir()
    types: dict = {}
    for f in sorted((root / "msg").glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"{PACKAGE}/msg/{f.stem}"))
    return types


@lru_cache(maxsize=1)
def typestore():
    """A ROS 2 Jazzy rosbags type store with soma_msgs registered (cached)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(soma_type_definitions())
    return store
