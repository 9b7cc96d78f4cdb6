"""The nodes' command-line number types: bad values are one-line usage errors (no ROS)."""

from __future__ import annotations

import pytest

from soma_ros.nodes import bag_player, recorder


@pytest.mark.parametrize("flag, value", [("--rate", "0"), ("--rate", "-2"), ("--rate", "nan"), ("--rate", "fast"),
                                         ("--start-offset", "-1"), ("--wait-for-subscribers", "-1"),
                                         ("--wait-for-subscribers", "1.5")])
def test_player_refuses_a_bad_number_in_one_line(flag, value, capsys):
    with pytest.raises(SystemExit) as e:
        bag_player.build_parser().parse_args(["b", flag, value])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert flag in err and f"got {value}" in err


def test_player_and_recorder_take_good_numbers():
    a = bag_player.build_parser().parse_args(["b", "--rate", "2.5", "--start-offset", "0",
                                              "--wait-for-subscribers", "0"])
    assert (a.rate, a.start_offset, a.wait_for_subscribers) == (2.5, 0.0, 0)
    r = recorder.build_parser().parse_args(["--out", "o", "--topics", "/joint_states", "--duration", "1.5", "--max-messages", "3"])
    assert (r.duration, r.max_messages) == (1.5, 3)


@pytest.mark.parametrize("argv", [["--duration", "0"], ["--max-messages", "0"], ["--queue", "-3"],
                                  ["--discovery-timeout", "inf"]])
def test_recorder_refuses_a_bad_number(argv, capsys):
    with pytest.raises(SystemExit) as e:
        recorder.build_parser().parse_args(["--out", "o", "--topics", "/joint_states", *argv])
    assert e.value.code == 2 and f"got {argv[1]}" in capsys.readouterr().err
