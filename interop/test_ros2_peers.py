"""rollbase's ROS 2 node with the peers users run (issue 26): callers on both request/reply
mappings served by one process (Eclipse Cyclone DDS through the Python `cyclonedds` package, and
a C++ peer of ours on Debian's eProsima Fast DDS, the DDS of ROS 2's default rmw, in
interop/fastdds_peer/), best-effort command publishers, the node's announcement on
`ros_discovery_info` in Humble's and Jazzy's layouts, and the robot model on
`robot_description` read by an independent URDF parser (urdf_parser_py).

The node runs as `rollbase ros2-selftest` (the real node on a synthetic state; every command it
passes on is printed as a JSON line). DDS discovery multicasts: like test_ros2_node.py these
tests run only inside a private network namespace whose only interface is loopback (.ci/run);
elsewhere they are skipped (ROLLBASE_REQUIRE_DDS=1: they fail)."""

import json
import os
import shutil
import signal
import subprocess
import time
import tomllib
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from conftest import REPO, binary
from test_ros2_node import SelfTest, only_loopback

NETNS_HINT = "run inside a private network namespace: unshare -n sh -c 'ip link set lo up; python3 -m pytest interop/test_ros2_peers.py'"

if os.environ.get("ROLLBASE_REQUIRE_DDS") == "1" and not only_loopback():
    raise RuntimeError(f"ROLLBASE_REQUIRE_DDS=1 but this is not a loopback-only network namespace: {NETNS_HINT}")

pytestmark = pytest.mark.skipif(not only_loopback(), reason=f"DDS test outside a private network namespace: {NETNS_HINT}")

if only_loopback():
    from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import array, sequence, uint8
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    import ros2_types as rt

    ROS_QOS = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.Durability.Volatile, Policy.History.KeepLast(10))
    BEST_EFFORT = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(10))
    LATCHED = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.Durability.TransientLocal, Policy.History.KeepLast(1))
    # A reader of latched topics keeps more: keyless samples of every writer are one instance,
    # so with depth 1 one participant's announcement replaces another's before it is taken.
    LATCHED_READER = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.Durability.TransientLocal, Policy.History.KeepLast(100))

    # rmw_dds_common/msg/ParticipantEntitiesInfo in both layouts, from the .msg files of Humble
    # (Gid: char[24] data) and Jazzy (Gid: uint8[16] data). Same DDS type names, as on the wire.
    @dataclass
    class Gid24(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
        data: array[uint8, 24] = field(default_factory=lambda: [0] * 24)

    @dataclass
    class Node24(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
        node_namespace: str = ""
        node_name: str = ""
        reader_gid_seq: sequence[Gid24] = field(default_factory=list)
        writer_gid_seq: sequence[Gid24] = field(default_factory=list)

    @dataclass
    class Info24(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
        gid: Gid24 = field(default_factory=Gid24)
        node_entities_info_seq: sequence[Node24] = field(default_factory=list)

    @dataclass
    class Gid16(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
        data: array[uint8, 16] = field(default_factory=lambda: [0] * 16)

    @dataclass
    class Node16(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
        node_namespace: str = ""
        node_name: str = ""
        reader_gid_seq: sequence[Gid16] = field(default_factory=list)
        writer_gid_seq: sequence[Gid16] = field(default_factory=list)

    @dataclass
    class Info16(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
        gid: Gid16 = field(default_factory=Gid16)
        node_entities_info_seq: sequence[Node16] = field(default_factory=list)

    LAYOUTS = {24: (Info24, Node24, Gid24), 16: (Info16, Node16, Gid16)}


def fastdds_peer() -> Path:
    """The C++ Fast DDS peer, built by interop/fastdds_peer/build.sh (.ci/run builds it)."""
    path = Path(os.environ.get("ROLLBASE_FASTDDS_PEER", REPO / "target" / "fastdds_peer"))
    if not path.exists():
        if shutil.which("g++") is None or not Path("/usr/include/fastdds").exists():
            raise FileNotFoundError(f"{path} is missing and cannot be built: apt-get install g++ libfastrtps-dev, then interop/fastdds_peer/build.sh")
        subprocess.run([str(REPO / "interop" / "fastdds_peer" / "build.sh"), str(path)], check=True, timeout=300)
    return path


def run_fastdds(domain, *args, timeout=60):
    """Runs the Fast DDS peer to its end; returns its JSON events (fails on exit ≠ 0)."""
    p = subprocess.run([str(fastdds_peer()), "--domain", str(domain), *args], capture_output=True, text=True, timeout=timeout)
    events = [json.loads(line) for line in p.stdout.splitlines() if line.startswith("{")]
    assert p.returncode == 0, f"Fast DDS peer failed (exit {p.returncode}): {events}\n{p.stderr[-2000:]}"
    return events


def matched(*endpoints, timeout=15.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if all((e.get_matched_subscriptions() if isinstance(e, DataWriter) else e.get_matched_publications()) for e in endpoints):
            return
        time.sleep(0.02)
    raise AssertionError("DDS discovery did not match the node's endpoints in time")


class CycloneClient:
    """A ~/srv client in rmw_cyclonedds' mapping; replies to other callers (the Fast DDS
    peer's, on the same reply topic) are ignored as rmw_cyclonedds ignores them."""

    def __init__(self, dp, fqn, srv):
        self.w = DataWriter(dp, Topic(dp, f"rq{fqn}/{srv}Request", rt.TriggerRequest, qos=ROS_QOS), qos=ROS_QOS)
        self.r = DataReader(dp, Topic(dp, f"rr{fqn}/{srv}Reply", rt.TriggerResponse, qos=ROS_QOS), qos=ROS_QOS)
        matched(self.w, self.r)
        time.sleep(0.3)  # the node's reply writer matches our reader on its own schedule
        self.seq = 0

    def call(self, guid=0x0A0B0C0D0E0F1011, timeout=10.0):
        self.seq += 1
        self.w.write(rt.TriggerRequest(client_guid=guid, sequence_number=self.seq))
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for s in self.r.take(N=10):
                if isinstance(s, rt.TriggerResponse) and (s.client_guid, s.sequence_number) == (guid, self.seq):
                    return s
            time.sleep(0.01)
        raise AssertionError(f"no reply in {timeout} s")


def test_cyclone_and_fast_dds_callers_served_by_one_process():
    """One rollbase process, no mapping flag: a Cyclone DDS caller and the Fast DDS peer both
    get their ~/stop and ~/rearm answered; the Fast DDS peer's odometry and cmd_vel go through."""
    domain = 21
    st = SelfTest("--ros2-domain-id", str(domain))
    try:
        dp = DomainParticipant(domain)
        stop = CycloneClient(dp, "/rollbase", "stop")
        rep = stop.call()
        assert rep.success and "stop passed to the cycle" in rep.message, rep.message
        st.next_json(lambda j: j.get("cmd") == "stop")
        events = run_fastdds(domain, "--twist", "0.25,-0.125,0.375", "--count", "3", "--calls", "stop,rearm")
        kinds = [e["event"] for e in events]
        assert kinds == ["matched", "odom", "sent", "reply", "reply", "done"], events
        odom = events[1]
        assert (odom["frame"], odom["child"]) == ("odom", "base_link"), odom
        # The synthetic state's twist (0.1, 0.05, 0.2), decoded by Fast CDR.
        assert (odom["vx"], odom["vy"], odom["wz"]) == (0.1, 0.05, 0.2), odom
        replies = {e["service"]: e for e in events if e["event"] == "reply"}
        assert replies["stop"]["success"] and "stop passed to the cycle" in replies["stop"]["message"], replies
        assert replies["rearm"]["success"] and "rearm passed to the cycle" in replies["rearm"]["message"], replies
        print("Fast DDS peer: discovery %.3f s, ~/stop answered in %.1f ms, ~/rearm in %.1f ms" % (
            events[0]["t"], replies["stop"]["ms"], replies["rearm"]["ms"]))
        motions = [st.next_json(lambda j: j.get("cmd") == "motion") for _ in range(3)]
        assert all((m["vx"], m["vy"], m["omega"]) == (0.25, -0.125, 0.375) for m in motions), motions
        st.next_json(lambda j: j.get("cmd") == "stop")
        st.next_json(lambda j: j.get("cmd") == "rearm")
        # The Cyclone caller again, after the Fast DDS calls, on the same node.
        rearm = CycloneClient(dp, "/rollbase", "rearm")
        rep = rearm.call()
        assert rep.success and "rearm passed to the cycle" in rep.message, rep.message
    finally:
        done = st.stop()
    s = done["stats"]
    assert (s["services_cyclone"], s["services_enhanced"], s["services_answered"]) == (2, 2, 4), s
    assert s["undecodable"] == {} and s["receive_errors"] == 0, s


def test_best_effort_cmd_vel_publishers_drive():
    """A best-effort cmd_vel publisher (Cyclone DDS, and the Fast DDS peer with --best-effort)
    is matched and its commands arrive; no incompatible-QoS event on cmd_vel. (leg_commands:
    test_best_effort_and_reliable_leg_publishers_both_match, test_a_best_effort_leg_publisher_moves_the_legs.)"""
    domain = 24
    st = SelfTest("--ros2-domain-id", str(domain))
    try:
        dp = DomainParticipant(domain)
        w = DataWriter(dp, Topic(dp, "rt/cmd_vel", rt.Twist, qos=BEST_EFFORT), qos=BEST_EFFORT)
        matched(w)
        st.publishers_matched("/cmd_vel")
        w.write(rt.Twist(linear=rt.Vector3(x=0.5, y=0.25), angular=rt.Vector3(z=-0.125)))
        got = st.next_json(lambda j: j.get("cmd") == "motion")
        assert (got["vx"], got["vy"], got["omega"]) == (0.5, 0.25, -0.125), got
        events = run_fastdds(domain, "--best-effort", "--twist", "0.0625,0,0", "--count", "3", "--calls", "")
        assert [e["event"] for e in events] == ["matched", "odom", "sent", "done"], events
        # Best effort may lose a sample in principle; on loopback none is lost, but one is enough.
        got = st.next_json(lambda j: j.get("cmd") == "motion" and j["vx"] == 0.0625)
        assert got["vy"] == 0.0 and got["omega"] == 0.0
    finally:
        done = st.stop()
    assert done["stats"]["qos_incompatible"] == 0, done
    assert done["stats"]["undecodable"] == {}, done


def test_best_effort_and_reliable_leg_publishers_both_match():
    """leg_commands is read best effort (docs/ros2.md, QoS), like cmd_vel: a best-effort and
    a reliable leg publisher both match, the commands of both arrive exactly, and no
    incompatible-QoS event is counted."""
    domain = 46
    st = SelfTest("--ros2-domain-id", str(domain))
    try:
        dp = DomainParticipant(domain)
        topic = Topic(dp, "rt/leg_commands", rt.Float64MultiArray, qos=ROS_QOS)
        be = DataWriter(dp, topic, qos=BEST_EFFORT)
        rel = DataWriter(dp, topic, qos=ROS_QOS)
        matched(be, rel)
        st.publishers_matched("/leg_commands", count=2)
        be.write(rt.Float64MultiArray(data=[0.3, 0.31, 0.32, 0.33]))
        assert st.next_json(lambda j: j.get("cmd") == "legs")["legs"] == [0.3, 0.31, 0.32, 0.33]
        rel.write(rt.Float64MultiArray(data=[0.4, 0.41, 0.42, 0.43]))
        assert st.next_json(lambda j: j.get("cmd") == "legs")["legs"] == [0.4, 0.41, 0.42, 0.43]
    finally:
        done = st.stop()
    assert done["stats"]["qos_incompatible"] == 0, done
    assert done["stats"]["undecodable"] == {} and done["stats"]["oversized"] == {}, done


def test_a_best_effort_leg_publisher_moves_the_legs(tmp_path):
    """`rollbase demo --ros2` (the simulated platform in real time) and a best-effort leg
    publisher (Cyclone DDS, as a joystick or teleop node may publish): repeated at 20 Hz, its
    targets move every leg there (joint_states within 1 mm), and the log has no
    incompatible-QoS line."""
    domain = 47
    cfg = subprocess.run([str(binary("rollbase")), "config", "default"], capture_output=True, text=True, timeout=30)
    assert cfg.returncode == 0, cfg.stderr
    wheels = tomllib.loads(cfg.stdout)["wheels"]
    # 20 mm from nominal, alternately out and in, inside each leg's range.
    targets = [min(max(w["lambda_nominal"] + (0.02 if i % 2 == 0 else -0.02), w["lambda_min"] + 0.005), w["lambda_max"] - 0.005)
               for i, w in enumerate(wheels)]
    log = tmp_path / "demo.log"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), RUST_LOG="info")
    with open(log, "w") as e:
        p = subprocess.Popen([str(binary("rollbase")), "demo", "--ros2"], stdout=subprocess.DEVNULL, stderr=e, env=env)
    try:
        end = time.monotonic() + 30
        while "state: tracking" not in log.read_text():
            assert p.poll() is None and time.monotonic() < end, log.read_text()
            time.sleep(0.05)
        dp = DomainParticipant(domain)
        legs_w = DataWriter(dp, Topic(dp, "rt/leg_commands", rt.Float64MultiArray, qos=BEST_EFFORT), qos=BEST_EFFORT)
        js_r = DataReader(dp, Topic(dp, "rt/joint_states", rt.JointState, qos=ROS_QOS), qos=ROS_QOS)
        matched(legs_w, js_r)
        time.sleep(0.2)
        names = [f"wheel_{i + 1}_leg_joint" for i in range(len(wheels))]
        start = last = None
        end = time.monotonic() + 15
        while time.monotonic() < end:
            legs_w.write(rt.Float64MultiArray(data=targets))
            for js in js_r.take(N=100):
                if isinstance(js, rt.JointState):
                    last = [js.position[js.name.index(n)] for n in names]
                    start = start or last
            if last and all(abs(x - t) <= 1e-3 for x, t in zip(last, targets)):
                break
            time.sleep(0.05)
        print(f"legs from {start} to {last}, targets {targets}")
        assert start is not None, "no joint_states"
        assert max(abs(x - t) for x, t in zip(start, targets)) > 0.015, "the legs started at the targets: nothing shown"
        assert all(abs(x - t) <= 1e-3 for x, t in zip(last, targets)), (last, targets)
        assert "incompatible QoS" not in log.read_text()
    finally:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


def guid_of(key: uuid.UUID) -> list:
    return list(key.bytes)


def endpoints(dp, builtin, topic_name, timeout=10.0):
    """The GUIDs of the endpoints on `topic_name` that DDS discovery reports."""
    r = BuiltinDataReader(dp, builtin)
    end = time.monotonic() + timeout
    found = set()
    while time.monotonic() < end and not found:
        for s in r.take(N=200):
            if getattr(s, "topic_name", None) == topic_name:
                found.add(bytes(guid_of(s.key)))
        time.sleep(0.05)
    return found


@pytest.mark.parametrize("layout", [24, 16], ids=["humble-24-byte-gid", "jazzy-16-byte-gid"])
def test_node_announced_in_the_peers_discovery_layout(layout):
    """A ROS 2 peer announces itself on ros_discovery_info in Humble's or Jazzy's layout;
    rollbase (no ROS_DISTRO, no option) answers in the same layout, and its announcement lists
    the node /rollbase with the GUIDs of its cmd_vel reader and odom writer, as DDS discovery
    reports them: what `ros2 node list` and `ros2 node info` read."""
    Info, Node, Gid = LAYOUTS[layout]
    domain = 25 if layout == 24 else 26
    env_distro = os.environ.pop("ROS_DISTRO", None)
    try:
        st = SelfTest("--ros2-domain-id", str(domain))
    finally:
        if env_distro is not None:
            os.environ["ROS_DISTRO"] = env_distro
    try:
        dp = DomainParticipant(domain)
        topic = Topic(dp, "ros_discovery_info", Info, qos=LATCHED)
        w = DataWriter(dp, topic, qos=LATCHED)
        r = DataReader(dp, topic, qos=LATCHED_READER)
        my_gid = Gid(data=list(range(1, 17)) + [0] * (layout - 16))
        w.write(Info(gid=my_gid, node_entities_info_seq=[Node(node_namespace="/", node_name="operator")]))
        t0 = time.monotonic()
        mine = None
        while mine is None and time.monotonic() < t0 + 15:
            for s in r.take(N=20):
                if isinstance(s, Info):
                    names = [(n.node_namespace, n.node_name) for n in s.node_entities_info_seq]
                    if ("/", "rollbase") in names:
                        mine = s
            time.sleep(0.02)
        assert mine is not None, f"no announcement of /rollbase in the {layout}-byte layout"
        print(f"{layout}-byte layout: /rollbase announced {time.monotonic() - t0:.3f} s after the peer's announcement")
        node = next(n for n in mine.node_entities_info_seq if n.node_name == "rollbase")
        if layout == 24:
            assert all(list(g.data)[16:] == [0] * 8 for g in node.reader_gid_seq + node.writer_gid_seq)
        readers = {bytes(list(g.data)[:16]) for g in node.reader_gid_seq}
        writers = {bytes(list(g.data)[:16]) for g in node.writer_gid_seq}
        assert readers & endpoints(dp, BuiltinTopicDcpsSubscription, "rt/cmd_vel"), "the cmd_vel reader is the node's"
        assert writers & endpoints(dp, BuiltinTopicDcpsPublication, "rt/odom"), "the odom writer is the node's"
        assert writers & endpoints(dp, BuiltinTopicDcpsPublication, "rr/rollbase/stopReply")
        assert readers & endpoints(dp, BuiltinTopicDcpsSubscription, "rq/rollbase/stopRequest")
        # cmd_vel, leg_commands and 8 service request readers; 6 topics and 8 reply writers.
        assert (len(readers), len(writers)) == (10, 14), (len(readers), len(writers))
    finally:
        done = st.stop()
    assert done["stats"]["discovery_layout"] == layout, done


def test_ros_distro_chooses_the_layout_without_a_peer():
    """With ROS_DISTRO=humble (a sourced Humble environment) the node announces itself in the
    24-byte layout at once; a late Jazzy-layout reader would not see it, a Humble one does."""
    domain = 27
    old = os.environ.get("ROS_DISTRO")
    os.environ["ROS_DISTRO"] = "humble"
    try:
        st = SelfTest("--ros2-domain-id", str(domain))
    finally:
        if old is None:
            os.environ.pop("ROS_DISTRO")
        else:
            os.environ["ROS_DISTRO"] = old
    try:
        dp = DomainParticipant(domain)
        r = DataReader(dp, Topic(dp, "ros_discovery_info", Info24, qos=LATCHED), qos=LATCHED_READER)
        end = time.monotonic() + 15
        seen = None
        while seen is None and time.monotonic() < end:
            for s in r.take(N=10):
                if isinstance(s, Info24) and any(n.node_name == "rollbase" for n in s.node_entities_info_seq):
                    seen = s
            time.sleep(0.02)
        assert seen is not None, "the transient-local announcement reached a late Humble-layout reader"
    finally:
        done = st.stop()
    assert done["stats"]["discovery_layout"] == 24, done


def test_robot_description_parsed_by_urdf_parser_py_has_the_joint_states_names():
    """robot_description (transient local: a late subscriber gets it) parsed by urdf_parser_py:
    its movable joints are exactly the names joint_states publishes, and every wheel link hangs
    from base_link through its leg and steering (the chain robot_state_publisher walks)."""
    from urdf_parser_py.urdf import URDF

    domain = 28
    st = SelfTest("--ros2-domain-id", str(domain))
    try:
        time.sleep(1.0)  # subscribe late: the description is latched
        dp = DomainParticipant(domain)
        rd = DataReader(dp, Topic(dp, "rt/robot_description", rt.String, qos=LATCHED), qos=LATCHED)
        js = DataReader(dp, Topic(dp, "rt/joint_states", rt.JointState, qos=ROS_QOS), qos=ROS_QOS)
        desc = joints = None
        end = time.monotonic() + 15
        while (desc is None or joints is None) and time.monotonic() < end:
            for s in rd.take(N=2):
                if isinstance(s, rt.String):
                    desc = s.data
            for s in js.take(N=5):
                if isinstance(s, rt.JointState):
                    joints = list(s.name)
            time.sleep(0.02)
        assert desc is not None and joints is not None, (desc is None, joints is None)
    finally:
        st.stop()
    robot = URDF.from_xml_string(desc.encode())
    movable = [j.name for j in robot.joints if j.type != "fixed"]
    assert sorted(movable) == sorted(joints), (movable, joints)
    assert robot.get_root() == "base_link"
    for i in range(1, len(joints) // 3 + 1):
        chain = robot.get_chain("base_link", f"wheel_{i}_link", links=False)
        assert chain == [f"wheel_{i}_leg_joint", f"wheel_{i}_steer_joint", f"wheel_{i}_drive_joint"], chain
        kinds = [robot.joint_map[j].type for j in chain]
        assert kinds == ["prismatic", "continuous", "continuous"], kinds


def test_incompatible_qos_is_logged_with_the_policy():
    """A subscriber that cannot match one of the node's endpoints (a transient-local reader of
    the volatile odom) is reported: counted, and logged once with the endpoint and the policy."""
    domain = 29
    st = SelfTest("--ros2-domain-id", str(domain))
    try:
        dp = DomainParticipant(domain)
        r = DataReader(dp, Topic(dp, "rt/odom", rt.Odometry, qos=ROS_QOS), qos=LATCHED_READER)
        end = time.monotonic() + 10
        while time.monotonic() < end and not any("incompatible QoS" in line for line in st.stderr_lines):
            time.sleep(0.05)
        assert not r.get_matched_publications(), "a transient-local reader does not match a volatile writer"
    finally:
        done = st.stop()
    assert done["stats"]["qos_incompatible"] >= 1, done
    lines = [line for line in st.stderr_lines if "incompatible QoS" in line]
    assert len(lines) == 1, lines
    assert "publisher /odom" in lines[0] and "policy Durability" in lines[0] and "TransientLocal" in lines[0], lines[0]


def test_dds_stack_logs_reach_the_log_under_rust_log():
    """rustdds' log records come out in rollbase's log, filtered by RUST_LOG: in this
    namespace (loopback without multicast) rustdds warns that it joined no multicast group;
    the default filter keeps rustdds at errors, RUST_LOG=info,rustdds=warn shows the warning."""
    from conftest import binary

    def run(rust_log):
        env = {k: v for k, v in os.environ.items() if k not in ("RUST_LOG", "ROS_DISTRO")}
        if rust_log is not None:
            env["RUST_LOG"] = rust_log
        p = subprocess.run([str(binary("rollbase")), "ros2-selftest", "--ros2-domain-id", "43", "--duration", "1.5"],
                           capture_output=True, text=True, timeout=60, env=env)
        assert p.returncode == 0, p.stderr[-2000:]
        return p.stderr

    quiet, loud = run(None), run("info,rustdds=warn")
    marker = "No multicast joins succeeded"
    assert marker not in quiet, quiet[-2000:]
    assert marker in loud and " WARN " in next(line for line in loud.splitlines() if marker in line), loud[-2000:]
    # The node's own lines are there either way.
    assert "ROS_DISTRO is not set" in quiet and "ROS_DISTRO is not set" in loud


def test_parameter_services_answer_like_any_node():
    """`ros2 param list` / `ros2 param set` reach rollbase's parameter services (in the
    caller's mapping): no parameters listed, a set refused with the reason."""
    domain = 44
    st = SelfTest("--ros2-domain-id", str(domain))
    try:
        dp = DomainParticipant(domain)

        def call(srv, req_t, rep_t, req):
            w = DataWriter(dp, Topic(dp, f"rq/rollbase/{srv}Request", req_t, qos=ROS_QOS), qos=ROS_QOS)
            r = DataReader(dp, Topic(dp, f"rr/rollbase/{srv}Reply", rep_t, qos=ROS_QOS), qos=ROS_QOS)
            matched(w, r)
            time.sleep(0.3)
            w.write(req)
            end = time.monotonic() + 10
            while time.monotonic() < end:
                for s in r.take(N=10):
                    if isinstance(s, rep_t) and (s.client_guid, s.sequence_number) == (req.client_guid, req.sequence_number):
                        return s
                time.sleep(0.01)
            raise AssertionError(f"no reply from ~/{srv}")

        lst = call("list_parameters", rt.ListParametersRequest, rt.ListParametersResponse,
                   rt.ListParametersRequest(client_guid=3, sequence_number=1, prefixes=[], depth=0))
        assert list(lst.names) == [] and list(lst.prefixes) == [], lst
        p = rt.Parameter(name="wheel_radius", value=rt.ParameterValue(type=3, double_value=0.1))
        rep = call("set_parameters", rt.SetParametersRequest, rt.SetParametersResponse,
                   rt.SetParametersRequest(client_guid=3, sequence_number=2, parameters=[p, p]))
        assert len(rep.results) == 2 and not any(r.successful for r in rep.results), rep
        assert "platform file" in rep.results[0].reason, rep.results[0].reason
    finally:
        done = st.stop()
    assert done["stats"]["services_cyclone"] == 2 and done["stats"]["undecodable"] == {}, done


def test_undecodable_samples_are_counted_per_endpoint_and_logged_once():
    """A publisher whose Twist has the right type name but the wrong layout, and a caller whose
    Trigger request fits neither mapping: nothing reaches the command port, each endpoint
    counts its samples, and each is logged once with the reason."""
    from cyclonedds.idl.types import float64 as f64, uint32, uint64

    @dataclass
    class ShortTwist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
        x: f64 = 0.0

    @dataclass
    class OddTrigger(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
        a: uint64 = 0
        b: uint32 = 0

    domain = 45
    st = SelfTest("--ros2-domain-id", str(domain))
    try:
        dp = DomainParticipant(domain)
        w = DataWriter(dp, Topic(dp, "rt/cmd_vel", ShortTwist, qos=ROS_QOS), qos=ROS_QOS)
        q = DataWriter(dp, Topic(dp, "rq/rollbase/stopRequest", OddTrigger, qos=ROS_QOS), qos=ROS_QOS)
        matched(w, q)
        st.publishers_matched("/cmd_vel")
        time.sleep(0.3)  # the stop service's request reader is reliable: its side settles too
        for k in range(3):
            w.write(ShortTwist(x=1.0 + k))
        q.write(OddTrigger(a=1, b=2))
        q.write(OddTrigger(a=3, b=4))
        end = time.monotonic() + 10
        while time.monotonic() < end and sum("did not decode" in line for line in st.stderr_lines) < 2:
            time.sleep(0.05)
        time.sleep(0.3)
    finally:
        done = st.stop()
    assert done["stats"]["undecodable"] == {"/cmd_vel": 3, "/rollbase/stop": 2}, done
    assert done["stats"]["commands_sent"] == 0 and done["stats"]["services_answered"] == 0, done
    assert not [c for c in st.commands if c["cmd"] in ("motion", "stop")], st.commands
    logged = [line for line in st.stderr_lines if "did not decode" in line]
    assert len(logged) == 2, logged
    vel = next(line for line in logged if "/cmd_vel" in line)
    srv = next(line for line in logged if "/rollbase/stop" in line)
    assert "geometry_msgs/msg/Twist" in vel, vel
    assert "fit neither mapping" in srv and "12 bytes" in srv, srv
