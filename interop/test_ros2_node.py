"""rollbase's ROS 2 node checked by an independent DDS peer: Eclipse Cyclone DDS (the C
library of ROS 2's rmw_cyclonedds, through the Python `cyclonedds` package) with the ROS 2
types declared in ros2_types.py. The node runs as `rollbase ros2-selftest`: the real node fed
with a synthetic 250 Hz state (every value a known function of time), printing each command it
passes to the cycle as a JSON line.

DDS discovery multicasts: these tests run only inside a private network namespace whose only
interface is loopback (.ci/run: `unshare -n sh -c 'ip link set lo up; …'`); anywhere else they
are skipped."""

import json
import math
import os
import queue
import subprocess
import threading
import time

import pytest

from conftest import binary

NETNS_HINT = "run inside a private network namespace: unshare -n sh -c 'ip link set lo up; python3 -m pytest interop/test_ros2_node.py'"


def only_loopback() -> bool:
    """Whether this process's network namespace has no interface but loopback (/proc/net/dev
    is per namespace; /sys/class/net may show the host's)."""
    try:
        with open("/proc/net/dev") as f:
            lines = f.read().splitlines()[2:]
    except OSError:
        return False
    ifaces = {line.split(":", 1)[0].strip() for line in lines if ":" in line}
    return ifaces == {"lo"}


if os.environ.get("ROLLBASE_REQUIRE_DDS") == "1" and not only_loopback():
    # .ci/run's namespaced stage: a skip there would hide that the tests never ran.
    raise RuntimeError(f"ROLLBASE_REQUIRE_DDS=1 but this is not a loopback-only network namespace: {NETNS_HINT}")

pytestmark = pytest.mark.skipif(not only_loopback(), reason=f"DDS test outside a private network namespace: {NETNS_HINT}")

if only_loopback():
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    import ros2_types as rt

    # ROS 2's default QoS (rmw_qos_profile_default): reliable, volatile, keep last 10.
    ROS_QOS = Qos(
        Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(10),
    )


class SelfTest:
    """`rollbase ros2-selftest` with its stdout lines collected by a thread."""

    def __init__(self, *extra):
        self.p = subprocess.Popen(
            [str(binary("rollbase")), "ros2-selftest", "--duration", "300", "--stdin-stop", *extra],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        self.lines = queue.Queue()
        self.commands = []
        self.stderr_lines = []
        threading.Thread(target=self._read, daemon=True).start()
        # Drained so that a chatty log never fills the pipe and blocks the node's threads.
        threading.Thread(target=self._read_stderr, daemon=True).start()
        self.ready = self.next_json(lambda j: j.get("ready"), timeout=20)

    def _read(self):
        for line in self.p.stdout:
            self.lines.put(line)

    def _read_stderr(self):
        for line in self.p.stderr:
            self.stderr_lines.append(line)

    def next_json(self, pred, timeout=10.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                line = self.lines.get(timeout=max(0.0, end - time.monotonic()))
            except queue.Empty:
                break
            j = json.loads(line)
            if "cmd" in j:
                self.commands.append(j)
            if pred(j):
                return j
        state = "exited" if self.p.poll() is not None else "still running"
        err = "".join(self.stderr_lines[-40:])
        raise AssertionError(f"selftest printed nothing matching in {timeout} s ({state}); stderr: {err}")

    def publishers_matched(self, endpoint, count=1, timeout=15.0):
        """Waits until the node logged that `count` publishers matched its best-effort reader
        of `endpoint` (e.g. "/cmd_vel"). The writer's own match (`matched`) is the other side
        of discovery: until the node has matched the writer too, rustdds drops its samples,
        and a best-effort reader never gets them again."""
        end = time.monotonic() + timeout
        want = f"ros2: {endpoint}: a publisher matched ({count} matched now)"
        while time.monotonic() < end:
            if any(want in line for line in self.stderr_lines):
                return
            time.sleep(0.01)
        err = "".join(self.stderr_lines[-40:])
        raise AssertionError(f"the node did not log '{want}' in {timeout} s; stderr: {err}")

    def stop(self):
        self.p.stdin.close()
        done = self.next_json(lambda j: j.get("done"), timeout=15)
        self.p.wait(timeout=10)
        return done


@pytest.fixture(scope="module")
def node():
    st = SelfTest()
    yield st
    if st.p.poll() is None:
        done = st.stop()
        assert done["stats"]["receive_errors"] == 0, done
        assert done["stats"]["publish_errors"] == 0, done


@pytest.fixture(scope="module")
def dp():
    return DomainParticipant(0)


def take(dp, name, ty, count, timeout=10.0, pred=lambda m: True):
    """`count` samples of topic `name` (DDS name rt/<name>) matching `pred`."""
    reader = DataReader(dp, Topic(dp, "rt" + name, ty, qos=ROS_QOS), qos=ROS_QOS)
    got = []
    end = time.monotonic() + timeout
    while len(got) < count and time.monotonic() < end:
        for s in reader.take(N=100):
            if isinstance(s, ty) and pred(s):
                got.append(s)
        time.sleep(0.005)
    assert len(got) >= count, f"{name}: {len(got)} of {count} samples in {timeout} s"
    return got[:count]


def matched(*endpoints, timeout=15.0):
    """Waits until every writer has a matched subscription and every reader a matched
    publication (a volatile sample written before discovery matched is lost by design)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if all(
            (e.get_matched_subscriptions() if isinstance(e, DataWriter) else e.get_matched_publications())
            for e in endpoints
        ):
            return
        time.sleep(0.02)
    raise AssertionError("DDS discovery did not match the node's endpoints in time")


def cov6(c3):
    """The documented mapping: (x, y, θ) → rows/cols 0, 1, 5; z, roll, pitch unobserved
    (variance 1e6, no correlation)."""
    idx = [0, 1, 5]
    out = [0.0] * 36
    for i in (2, 3, 4):
        out[i * 6 + i] = 1e6
    for r, rr in enumerate(idx):
        for k, cc in enumerate(idx):
            out[rr * 6 + cc] = c3[r][k]
    return out


def yaw(q):
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def test_odometry_field_by_field(node, dp):
    odoms = take(dp, "/odom", rt.Odometry, 10)
    now = time.time()
    for o in odoms:
        assert o.header.frame_id == "odom"
        assert o.child_frame_id == "base_link"
        stamp = o.header.stamp.sec + o.header.stamp.nanosec * 1e-9
        assert abs(stamp - now) < 30, (stamp, now)
        assert 0 <= o.header.stamp.nanosec < 1_000_000_000
        assert list(o.pose.covariance) == cov6(node.ready["pose_covariance"])
        assert list(o.twist.covariance) == cov6(node.ready["twist_covariance"])
        # Synthetic motion: x = 0.1 t, y = 0.05 t, θ = 0.2 t; twist (0.1, 0.05, 0.2).
        p = o.pose.pose
        assert p.position.z == 0.0
        assert math.isclose(p.position.x, 2 * p.position.y, rel_tol=1e-12, abs_tol=1e-15)
        th = 2 * p.position.x
        assert abs(math.remainder(yaw(p.orientation) - th, 2 * math.pi)) < 1e-9
        assert (p.orientation.x, p.orientation.y) == (0.0, 0.0)
        t = o.twist.twist
        assert (t.linear.x, t.linear.y, t.linear.z) == (0.1, 0.05, 0.0)
        assert (t.angular.x, t.angular.y, t.angular.z) == (0.0, 0.0, 0.2)
    # 50 Hz: consecutive stamps 20 ms apart on cycle time (x advances 0.1 × 0.02 m).
    dx = [b.pose.pose.position.x - a.pose.pose.position.x for a, b in zip(odoms, odoms[1:])]
    assert all(abs(d - 0.002) < 1e-9 for d in dx), dx


def test_tf_matches_odom(node, dp):
    reader_odom = DataReader(dp, Topic(dp, "rt/odom", rt.Odometry, qos=ROS_QOS), qos=ROS_QOS)
    reader_tf = DataReader(dp, Topic(dp, "rt/tf", rt.TFMessage, qos=ROS_QOS), qos=ROS_QOS)
    odoms, tfs = {}, {}
    end = time.monotonic() + 10
    while time.monotonic() < end and len(set(odoms) & set(tfs)) < 5:
        for o in reader_odom.take(N=100):
            if isinstance(o, rt.Odometry):
                odoms[(o.header.stamp.sec, o.header.stamp.nanosec)] = o
        for m in reader_tf.take(N=100):
            if isinstance(m, rt.TFMessage):
                assert len(m.transforms) == 1
                ts = m.transforms[0]
                tfs[(ts.header.stamp.sec, ts.header.stamp.nanosec)] = ts
        time.sleep(0.005)
    common = set(odoms) & set(tfs)
    assert len(common) >= 5, (len(odoms), len(tfs))
    for k in common:
        o, ts = odoms[k], tfs[k]
        assert ts.header.frame_id == "odom" and ts.child_frame_id == "base_link"
        assert (ts.transform.translation.x, ts.transform.translation.y, ts.transform.translation.z) == (
            o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z)
        r, q = ts.transform.rotation, o.pose.pose.orientation
        assert (r.x, r.y, r.z, r.w) == (q.x, q.y, q.z, q.w)


def test_joint_states_names_and_values(node, dp):
    n = node.ready["wheels"]
    for js in take(dp, "/joint_states", rt.JointState, 3):
        names = [f"wheel_{i}_{j}_joint" for i in range(1, n + 1) for j in ("steer", "drive", "leg")]
        assert list(js.name) == names
        assert len(js.position) == len(js.velocity) == 3 * n
        assert list(js.effort) == []
        for i in range(n):
            steer, drive, leg = js.position[3 * i: 3 * i + 3]
            vsteer, vdrive, vleg = js.velocity[3 * i: 3 * i + 3]
            assert math.isclose(steer, 0.1 * i, abs_tol=1e-15)
            assert math.isclose(leg, 0.4 + 0.01 * i, rel_tol=1e-15)
            assert (vsteer, vdrive) == (0.01 * i, 1.0 + i)
            assert math.isclose(vleg, 0.001 * i, abs_tol=1e-18)
            # wheel angle = (1 + i) t, so it is (1 + i) times wheel 1's.
            assert math.isclose(drive, (1 + i) * js.position[1], rel_tol=1e-12, abs_tol=1e-12)


def test_diagnostics_arrive_with_one_status_per_module_bus_and_supervisor(node, dp):
    n = node.ready["wheels"]
    arrays = take(dp, "/diagnostics", rt.DiagnosticArray, 1, timeout=5)
    names = [s.name for s in arrays[0].status]
    assert names == [f"rollbase: wheel {i} (node {i})" for i in range(1, n + 1)] + [
        "rollbase: CAN bus", "rollbase: supervisor"]
    by_name = {s.name: s for s in arrays[0].status}
    w1 = {kv.key: kv.value for kv in by_name["rollbase: wheel 1 (node 1)"].values}
    # The CiA 402 EMCY counts and history (issue 24) are there for every module, zero and "-"
    # (none came) on the synthetic state.
    assert w1 == {"rejected": "0", "late": "0", "lost": "0", "watchdog_trips": "0", "age_cycles": "0", "state": "enabled",
                  "emcy_informational": "0", "emcy_faults": "0", "emcy_last": "-"}
    assert all(s.level == 0 for s in arrays[0].status), [(s.name, s.level, s.message) for s in arrays[0].status]
    bus = {kv.key: kv.value for kv in by_name["rollbase: CAN bus"].values}
    assert float(bus["load"]) == 0.3


def test_twist_and_leg_commands_arrive_exactly(node, dp):
    w_vel = DataWriter(dp, Topic(dp, "rt/cmd_vel", rt.Twist, qos=ROS_QOS), qos=ROS_QOS)
    w_leg = DataWriter(dp, Topic(dp, "rt/leg_commands", rt.Float64MultiArray, qos=ROS_QOS), qos=ROS_QOS)
    matched(w_vel, w_leg)
    node.publishers_matched("/cmd_vel")
    node.publishers_matched("/leg_commands")
    cmd = rt.Twist(linear=rt.Vector3(x=0.123456789012345, y=-0.25, z=7.0), angular=rt.Vector3(x=1.0, y=2.0, z=-0.7071067811865476))
    w_vel.write(cmd)
    got = node.next_json(lambda j: j.get("cmd") == "motion")
    assert (got["vx"], got["vy"], got["omega"]) == (0.123456789012345, -0.25, -0.7071067811865476)
    assert got["legs"] is None
    legs = [0.4, 0.45000000000000007, 0.5, 0.41]
    w_leg.write(rt.Float64MultiArray(data=legs))
    got = node.next_json(lambda j: j.get("cmd") == "legs")
    assert got["legs"] == legs and got["n"] == 4
    assert got["t"] > 0


def test_stop_and_rearm_services_answer_honestly(node, dp):
    fqn = node.ready["node"]
    answers = {}
    for srv in ("stop", "rearm"):
        req_w = DataWriter(dp, Topic(dp, f"rq{fqn}/{srv}Request", rt.TriggerRequest, qos=ROS_QOS), qos=ROS_QOS)
        rep_r = DataReader(dp, Topic(dp, f"rr{fqn}/{srv}Reply", rt.TriggerResponse, qos=ROS_QOS), qos=ROS_QOS)
        matched(req_w, rep_r)
        time.sleep(0.2)  # the node's reply writer matched our reader: let its side settle too
        guid = 0x1122334455667788
        req_w.write(rt.TriggerRequest(client_guid=guid, sequence_number=7))
        end = time.monotonic() + 10
        rep = None
        while rep is None and time.monotonic() < end:
            for s in rep_r.take(N=10):
                if isinstance(s, rt.TriggerResponse):
                    rep = s
            time.sleep(0.01)
        assert rep is not None, f"no reply from {srv}"
        assert (rep.client_guid, rep.sequence_number) == (guid, 7), "the reply names our request"
        answers[srv] = rep
        node.next_json(lambda j, srv=srv: j.get("cmd") == srv)
        if srv == "stop":
            st = take(dp, "/supervisor_state", rt.String, 1, timeout=5, pred=lambda m: m.data.startswith("stopped"))
            assert st[0].data == "stopped"
    assert answers["stop"].success and "stop passed to the cycle" in answers["stop"].message
    assert answers["rearm"].success and "rearm passed to the cycle" in answers["rearm"].message
    assert "cause that persists keeps the fault latched" in answers["rearm"].message
    take(dp, "/supervisor_state", rt.String, 1, timeout=5, pred=lambda m: m.data == "tracking")


def test_stamped_velocity_in_a_foreign_frame_is_refused(dp):
    st = SelfTest("--ros2-cmd-vel-stamped", "--ros2-namespace", "/robot2", "--ros2-node-name", "base")
    try:
        assert st.ready["node"] == "/robot2/base"
        w = DataWriter(dp, Topic(dp, "rt/robot2/cmd_vel", rt.TwistStamped, qos=ROS_QOS), qos=ROS_QOS)
        matched(w)
        st.publishers_matched("/robot2/cmd_vel")
        hdr = rt.Header(stamp=rt.Time(sec=1, nanosec=2), frame_id="map")
        w.write(rt.TwistStamped(header=hdr, twist=rt.Twist(linear=rt.Vector3(x=9.0))))
        w.write(rt.TwistStamped(header=rt.Header(frame_id="base_link"), twist=rt.Twist(linear=rt.Vector3(x=0.5))))
        got = st.next_json(lambda j: j.get("cmd") == "motion")
        assert got["vx"] == 0.5, "the command in frame map was not passed on"
        # The namespaced odometry is on rt/robot2/odom.
        take(dp, "/robot2/odom", rt.Odometry, 1)
    finally:
        done = st.stop()
    assert done["stats"]["commands_refused"] == 1, done
    assert done["stats"]["commands_sent"] == 1, done


def test_recorded_state_topics_read_by_both_bag_readers(tmp_path):
    """The recorder writes what the node publishes: a selftest run with --record read back by
    rosbags (types from the file) and mcap-ros2-support."""
    from collections import Counter

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    bag = tmp_path / "selftest.mcap"
    st = SelfTest("--record", str(bag))
    time.sleep(2.5)
    done = st.stop()
    expected = done["recorded_messages"]
    assert {"/odom", "/tf", "/joint_states", "/diagnostics", "/supervisor_state"} <= set(expected), expected
    counts = Counter()
    with AnyReader([bag]) as r:
        for conn, ts, raw in r.messages():
            m = r.deserialize(raw, conn.msgtype)
            counts[conn.topic] += 1
            if conn.topic == "/odom":
                assert conn.msgtype == "nav_msgs/msg/Odometry"
                assert (m.header.frame_id, m.child_frame_id) == ("odom", "base_link")
                assert list(m.pose.covariance) == cov6(st.ready["pose_covariance"])
            if conn.topic == "/joint_states":
                assert len(m.name) == 12
    assert dict(counts) == expected
    with open(bag, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        n = Counter(ch.topic for _, ch, _, _ in reader.iter_decoded_messages())
    assert dict(n) == expected
    # 50 Hz odometry over the run's cycles (one every 5 cycles, the first at cycle 0).
    assert expected["/odom"] == (done["stats"]["cycles"] + 4) // 5
