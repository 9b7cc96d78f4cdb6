"""The demo report reads the live bag, and refuses in one line a bag whose soma_msgs types were
recorded with another soma_msgs version (a definition that differs from this install's)."""

from __future__ import annotations

import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from soma_ros.bagtypes import typestore
from soma_ros.data.bags import BagError
from soma_ros.demo_report import _read_live

STATUS = "soma_msgs/msg/SimStatus"


def _write_status_bag(path, store, storage):
    msg = store.types[STATUS]
    fields = {name: None for name, _ in store.fielddefs[STATUS][1]}
    writer = Writer(path, version=9, storage_plugin=storage)
    writer.open()
    try:
        conn = writer.add_connection("/soma/status", STATUS, typestore=store)
        Header = store.types["std_msgs/msg/Header"]
        Time = store.types["builtin_interfaces/msg/Time"]
        values = {}
        for name, (kind, spec) in store.fielddefs[STATUS][1]:
            if name == "header":
                values[name] = Header(stamp=Time(sec=1, nanosec=0), frame_id="soma_sim")
            elif spec == "string" or (isinstance(spec, tuple) and spec[0] == "string"):
                values[name] = "running"
            elif kind == 1 and spec in ("float32", "float64"):
                values[name] = 0.0
            elif kind == 1 and spec == "bool":
                values[name] = False
            else:
                values[name] = 0
        assert set(values) == set(fields)
        writer.write(conn, 1_000_000_000, store.serialize_cdr(msg(**values), STATUS))
    finally:
        writer.close()


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_a_bag_of_this_soma_msgs_is_read(tmp_path, storage):
    bag = tmp_path / "live"
    _write_status_bag(bag, typestore(), storage)
    live = _read_live(bag, [])
    assert len(live["status"]) == 1 and live["status"][0].state == "running"


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_a_bag_of_another_soma_msgs_version_is_refused_in_one_line(tmp_path, storage):
    """The same type name with one more field: the bag's RIHS01 hash differs from this install's."""
    from soma_ros.bagtypes import interface_dir

    text = (interface_dir() / "msg" / "SimStatus.msg").read_text() + "\nfloat32 added_in_another_version\n"
    other = get_typestore(Stores.ROS2_JAZZY)
    other.register(get_types_from_msg(text, STATUS))
    bag = tmp_path / "live_other"
    _write_status_bag(bag, other, storage)
    with pytest.raises(BagError) as err:
        _read_live(bag, [])
    line = str(err.value)
    assert "\n" not in line
    assert line.startswith("live_other: /soma/status [soma_msgs/msg/SimStatus]"), line
    assert "another soma_msgs version" in line
