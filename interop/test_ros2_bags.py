"""rollbase recordings read as ROS 2 bags by two independent readers: `rosbags` (builds its
types only from the .msg text stored in the file's schemas) and `mcap-ros2-support` (the
decoder of the mcap project, used by Foxglove's tooling). Every message of a demo recording
must decode, and the counts must equal what the run reported (`recorded_messages`). No DDS
here: these run anywhere."""

import json
import math
import shutil
import subprocess
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader

from conftest import binary, rollbase


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """`rollbase demo --lockstep --record X --json`: (summary JSON, path)."""
    d = tmp_path_factory.mktemp("bag")
    rec = d / "seed000.mcap"
    out = rollbase("demo", "--lockstep", "--scenario", "seed000", "--json", "--record", str(rec), timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout), rec


def test_rosbags_decodes_every_message_from_the_schema_text(recording):
    summary, rec = recording
    expected = summary["recorded_messages"]
    counts = Counter()
    with AnyReader([rec]) as reader:  # no default typestore: types come from the file only
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types["/can/rx"] == "can_msgs/msg/Frame"
        assert types["/pose"] == "rollbase_msgs/msg/Pose"
        for conn, ts, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] += 1
            if conn.topic == "/pose":
                assert msg.has_truth and math.isfinite(msg.x), msg
                assert msg.header.frame_id == "odom"
                assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == ts
            elif conn.topic == "/can/tx":
                assert msg.dlc <= 8 and len(msg.data) == 8 and not msg.is_extended
            elif conn.topic == "/icr":
                assert len(msg.wheel_x) == len(msg.wheel_y) == 4
    assert dict(counts) == expected


def test_mcap_ros2_support_decodes_every_message(recording):
    summary, rec = recording
    expected = summary["recorded_messages"]
    counts = Counter()
    cycles = set()
    with open(rec, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            counts[channel.topic] += 1
            if channel.topic == "/supervisor":
                cycles.add(decoded.cycle)
                assert decoded.state in {"idle", "aligning", "tracking", "stopping", "stopped", "fault"}
            elif channel.topic == "/feedback":
                assert [w.node for w in decoded.wheels] == [1, 2, 3, 4]
    assert dict(counts) == expected
    assert len(cycles) == summary["cycles"], "one /supervisor message per cycle"


def test_both_readers_agree_value_for_value_on_the_pose(recording):
    _, rec = recording
    with AnyReader([rec]) as r:
        conns = [c for c in r.connections if c.topic == "/pose"]
        a = [(m.cycle, m.x, m.y, m.theta) for m in (r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns))]
    with open(rec, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        b = [(d.cycle, d.x, d.y, d.theta) for _, _, _, d in reader.iter_decoded_messages(topics=["/pose"])]
    assert a == b and len(a) > 1000


def test_recover_salvages_a_recording_cut_like_after_kill_9(recording, tmp_path):
    summary, rec = recording
    data = rec.read_bytes()
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(data[: len(data) // 2])
    before = broken.read_bytes()
    out = rollbase("recover", str(broken), "--out", str(tmp_path / "fixed.mcap"))
    assert out.returncode == 0, out.stderr
    assert broken.read_bytes() == before, "the input is never modified"
    fixed = Path(out.stdout.strip())
    assert fixed == tmp_path / "fixed.mcap"
    total = sum(summary["recorded_messages"].values())
    with open(fixed, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        n = sum(1 for _ in reader.iter_decoded_messages())
        stats = reader.get_summary().statistics
    assert stats.message_count == n
    # Half the bytes hold about half the messages, less the torn chunk (at most 256 KiB).
    assert total * 0.35 < n < total * 0.55, (n, total)
    assert f"recovered {n} messages" in out.stderr, out.stderr
    with AnyReader([fixed]) as r:
        assert sum(1 for _ in r.messages()) == n
    # Running it again does not overwrite the output.
    again = rollbase("recover", str(broken), "--out", str(fixed))
    assert again.returncode != 0 and "exists" in again.stderr, again.stderr


def test_ros2_bag_info_if_installed(recording):
    """`ros2 bag info` (rosbag2 with the mcap storage plugin) when a ROS 2 installation is on
    PATH; CI machines have none, so this usually says skipped."""
    if shutil.which("ros2") is None:
        pytest.skip("no ROS 2 installation (ros2 not on PATH)")
    _, rec = recording
    out = subprocess.run(["ros2", "bag", "info", "-s", "mcap", str(rec)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "/pose" in out.stdout and "can_msgs/msg/Frame" in out.stdout


def test_message_definitions_hash_like_upstream_ros2():
    """Each standard type rollbase declares, parsed by rosbags from rollbase's .msg text, has
    the same RIHS01 type hash (names, types and order of every field, nested types included)
    as the ROS 2 Jazzy definition rosbags ships."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    out = rollbase("ros2-msg-definitions")
    assert out.returncode == 0, out.stderr
    defs = json.loads(out.stdout)
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    checked = []
    for name, text in defs.items():
        if "/srv/" in name:
            continue  # service parts are never bag schemas; rosbags names them differently
        ours = get_typestore(Stores.EMPTY)
        ours.register(get_types_from_msg(text, name))
        assert name in ours.fielddefs, name
        if name in jazzy.fielddefs:
            assert ours.hash_rihs01(name) == jazzy.hash_rihs01(name), name
            checked.append(name)
    for must in ("nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/JointState",
                 "diagnostic_msgs/msg/DiagnosticArray", "std_msgs/msg/Float64MultiArray",
                 "geometry_msgs/msg/TwistStamped", "std_msgs/msg/String"):
        assert must in checked, (must, checked)
