"""Several bases and several hosts (issue 26):

- a fleet: 4 simulated bases (`rollbase demo --ros2 --ros2-namespace /robotN`, each a whole
  base: simulator, 250 Hz cycle and node in one process) in one DDS domain, driven by one Eclipse
  Cyclone DDS peer: discovery time, each base's node in `ros_discovery_info`, a command to one
  base moves that base only, CPU and memory per base;
- two hosts: a "robot" and an "operator" network namespace joined by a veth pair, multicast
  discovery across the link (a route for 239.255.0.0/16 on the veth), `demo --ros2` on the
  robot, interop/ros2_operator.py (Cyclone DDS) on the operator: discovery time, cmd_vel → odom,
  odom latency across the link, ~/stop.

Every figure is printed (run pytest with -s to see them; docs/ros2.md and docs/performance.md
quote a run). DDS multicasts: the fleet runs in the loopback-only namespace the other ROS 2
tests use, the two hosts in namespaces this test creates (`ip netns add`, removed at the end);
outside a loopback-only namespace everything here is skipped (ROLLBASE_REQUIRE_DDS=1: fails).
The time is bounded: about 25 s for the fleet, 20 s for the two hosts."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO, binary, rollbase  # noqa: F401
from test_ros2_node import only_loopback

NETNS_HINT = "run inside a private network namespace: unshare -n sh -c 'ip link set lo up; python3 -m pytest interop/test_ros2_fleet.py'"

if os.environ.get("ROLLBASE_REQUIRE_DDS") == "1" and not only_loopback():
    raise RuntimeError(f"ROLLBASE_REQUIRE_DDS=1 but this is not a loopback-only network namespace: {NETNS_HINT}")

pytestmark = pytest.mark.skipif(not only_loopback(), reason=f"DDS test outside a private network namespace: {NETNS_HINT}")

if only_loopback():
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    import ros2_types as rt
    from test_ros2_demo import READER_QOS, REST_TOL, ROS_QOS, Demo, platform_file, speed
    from test_ros2_peers import LATCHED, LATCHED_READER, Gid16, Info16, Node16

BASES = 4
CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid):
    """User + system CPU seconds of a process (/proc/PID/stat)."""
    with open(f"/proc/{pid}/stat") as f:
        rest = f.read().rsplit(")", 1)[1].split()
    return (int(rest[11]) + int(rest[12])) / CLK_TCK


def status_kib(pid, key):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1])
    return 0


@pytest.fixture(scope="module")
def plat(tmp_path_factory):
    return platform_file(tmp_path_factory.mktemp("platform"))


def test_four_bases_in_one_domain_driven_by_one_peer(tmp_path, plat):
    domain = 31
    demos = []
    for i in range(1, BASES + 1):
        d = tmp_path / f"robot{i}"
        d.mkdir()
        demos.append(Demo(d, plat[0], domain, "--ros2-namespace", f"/robot{i}"))
    try:
        for i, d in enumerate(demos, 1):
            d.wait_log(rf"ROS 2 node /robot{i}/rollbase on DDS domain {domain}\b")
        for d in demos:
            d.wait_log(r"state: tracking")
        # One peer for the fleet: odom readers and cmd_vel writers of every base, and an
        # announcement of its own (Jazzy layout) to which the bases answer with theirs.
        t0 = time.monotonic()
        dp = DomainParticipant(domain)
        odom = [DataReader(dp, Topic(dp, f"rt/robot{i}/odom", rt.Odometry, qos=ROS_QOS), qos=READER_QOS)
                for i in range(1, BASES + 1)]
        cmd = [DataWriter(dp, Topic(dp, f"rt/robot{i}/cmd_vel", rt.Twist, qos=ROS_QOS), qos=ROS_QOS)
               for i in range(1, BASES + 1)]
        disc = Topic(dp, "ros_discovery_info", Info16, qos=LATCHED)
        DataWriter(dp, disc, qos=LATCHED).write(
            Info16(gid=Gid16(data=list(range(16))), node_entities_info_seq=[Node16(node_namespace="/", node_name="fleet_operator")]))
        disc_r = DataReader(dp, disc, qos=LATCHED_READER)
        matched_at = [None] * BASES
        while not all(matched_at):
            assert time.monotonic() - t0 < 30, f"discovery: bases matched {matched_at} after 30 s"
            for k in range(BASES):
                if matched_at[k] is None and odom[k].get_matched_publications() and cmd[k].get_matched_subscriptions():
                    matched_at[k] = time.monotonic() - t0
            time.sleep(0.005)
        nodes = set()
        want = {f"/robot{i}/rollbase" for i in range(1, BASES + 1)}
        while not want <= nodes and time.monotonic() - t0 < 30:
            for s in disc_r.take(N=50):
                if isinstance(s, Info16):
                    nodes |= {f"{n.node_namespace}/{n.node_name}" for n in s.node_entities_info_seq}
            time.sleep(0.01)
        announced_at = time.monotonic() - t0
        assert want <= nodes, nodes

        samples = [[] for _ in range(BASES)]

        def poll():
            for k in range(BASES):
                samples[k].extend(s for s in odom[k].take(N=500) if isinstance(s, rt.Odometry))

        # CPU and memory over the driving phases (every base publishing at its rates; one
        # driven at a time).
        pids = [d.p.pid for d in demos]
        cpu0 = [cpu_s(p) for p in pids]
        w0 = time.monotonic()

        def drive(k, twist, seconds):
            start = len(samples[k])
            t = time.monotonic()
            moved = None
            while time.monotonic() - t < seconds:
                cmd[k].write(twist)
                time.sleep(0.05)
                poll()
                if moved is None and any(speed(o) > REST_TOL for o in samples[k][start:]):
                    moved = time.monotonic() - t
            return moved

        poll()
        marks = [len(s) for s in samples]
        first_motion = drive(0, rt.Twist(linear=rt.Vector3(x=0.2)), 3.0)
        assert first_motion is not None, "robot1 did not move on its cmd_vel"
        moved1 = samples[0][marks[0]:]
        assert max(o.twist.twist.linear.x for o in moved1) > 0.15
        for k in (1, 2, 3):
            rest = samples[k][marks[k]:]
            assert len(rest) > 100 and all(speed(o) < REST_TOL for o in rest), f"robot{k + 1} moved on robot1's command"
        marks = [len(s) for s in samples]
        assert drive(2, rt.Twist(angular=rt.Vector3(z=0.3)), 2.5) is not None, "robot3 did not turn on its cmd_vel"
        assert max(o.twist.twist.angular.z for o in samples[2][marks[2]:]) > 0.25
        for k in (1, 3):
            rest = samples[k][marks[k]:]
            assert rest and all(speed(o) < REST_TOL for o in rest), f"robot{k + 1} moved on robot3's command"
        wall = time.monotonic() - w0
        cpu = [(cpu_s(p) - c) / wall for p, c in zip(pids, cpu0)]
        rss = [status_kib(p, "VmRSS:") / 1024 for p in pids]
        hwm = [status_kib(p, "VmHWM:") / 1024 for p in pids]
        threads = [status_kib(p, "Threads:") for p in pids]
        received = [len(s) for s in samples]
        print(f"\nfleet of {BASES} bases, one domain: discovery (peer start → every base's odom and cmd_vel matched) "
              f"{max(matched_at):.3f} s (per base {', '.join(f'{x:.3f}' for x in matched_at)} s); "
              f"all {BASES} nodes in ros_discovery_info after {announced_at:.3f} s; "
              f"robot1: cmd_vel → odom moving {first_motion:.3f} s (wheel alignment + ramp)")
        for k in range(BASES):
            print(f"robot{k + 1}: CPU {cpu[k] * 100:.1f} % of one core over {wall:.1f} s, RSS {rss[k]:.1f} MiB "
                  f"(peak {hwm[k]:.1f} MiB), {threads[k]} threads, {received[k]} odom received")
        # A sanity bound, not a performance assertion: a base that spins (100 % of a core)
        # or leaks (hundreds of MiB) is broken, whatever the machine.
        assert all(c < 0.6 for c in cpu), cpu
        assert all(h < 300 for h in hwm), hwm
        results = {"discovery_s": matched_at, "announced_s": announced_at, "first_motion_s": first_motion,
                   "cpu_fraction": cpu, "rss_mib": rss, "hwm_mib": hwm, "threads": threads, "window_s": wall}
        (REPO / "target").mkdir(exist_ok=True)
        (REPO / "target" / "ros2-fleet.json").write_text(json.dumps(results, indent=1))
        # Every base ends cleanly; the ones never commanded passed on no command. A base whose
        # simulated modules were held back for 16 ms by the shared host faults on stale
        # feedback by design (the supervisor doing its job, as in test_ros2_demo.py's bridge
        # test): printed, not a failure of the ROS 2 path; any other fault fails.
        for i, d in enumerate(demos, 1):
            rc, summary = d.terminate(signal.SIGTERM)
            assert summary, (i, rc, d.text()[-2000:])
            if (summary["fault_reason"] or "").startswith("stale feedback"):
                print(f"robot{i}: {summary['fault_reason']} (a host stall; {summary['deadline_misses']} deadline misses)")
            else:
                assert rc == 0 and summary["fault_reason"] is None, (i, rc, summary, d.text()[-2000:])
            m = re.search(r"ROS 2 node: (\d+) commands passed on", d.text())
            assert m, d.text()[-2000:]
            if i in (2, 4):
                assert int(m.group(1)) == 0, f"robot{i} took another base's commands"
            else:
                assert int(m.group(1)) > 0
    finally:
        for d in demos:
            d.kill()


# ---------------------------------------------------------------------------------------------
# Two hosts: a veth pair between two network namespaces of our own
# ---------------------------------------------------------------------------------------------


def sh(*args, check=True):
    return subprocess.run(list(args), capture_output=True, text=True, timeout=30, check=check)


@pytest.fixture
def two_hosts():
    """Namespaces `rb-robot-PID` (10.77.0.1/24) and `rb-operator-PID` (10.77.0.2/24) joined by
    a veth pair, multicast on, a route for 239.255.0.0/16 (DDS discovery) on the veth; only
    these two namespaces exist on the link. Removed at the end."""
    if subprocess.run(["ip", "netns", "list"], capture_output=True).returncode != 0:
        pytest.fail("`ip netns` is not available (iproute2)")
    tag = os.getpid()
    robot, op = f"rb-robot-{tag}", f"rb-operator-{tag}"
    va, vb = f"rbv{tag % 100000}a", f"rbv{tag % 100000}b"
    try:
        sh("ip", "netns", "add", robot)
        sh("ip", "netns", "add", op)
        sh("ip", "link", "add", va, "netns", robot, "type", "veth", "peer", "name", vb, "netns", op)
        for ns, dev, addr in ((robot, va, "10.77.0.1/24"), (op, vb, "10.77.0.2/24")):
            sh("ip", "-n", ns, "link", "set", "lo", "up")
            sh("ip", "-n", ns, "addr", "add", addr, "dev", dev)
            sh("ip", "-n", ns, "link", "set", dev, "multicast", "on")
            sh("ip", "-n", ns, "link", "set", dev, "up")
            sh("ip", "-n", ns, "route", "add", "239.255.0.0/16", "dev", dev)
        yield robot, op
    finally:
        sh("ip", "netns", "del", robot, check=False)
        sh("ip", "netns", "del", op, check=False)


def test_two_hosts_over_a_veth_link(tmp_path, plat, two_hosts):
    robot, op = two_hosts
    domain = 33
    log = open(tmp_path / "robot.log", "w")
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), RUST_LOG="info")
    p = subprocess.Popen(["ip", "netns", "exec", robot, str(binary("rollbase")), "demo", "--ros2", "--config", str(plat[0]), "--json"],
                         stdout=open(tmp_path / "robot.json", "w"), stderr=log, env=env)
    try:
        end = time.monotonic() + 30
        while "state: tracking" not in (tmp_path / "robot.log").read_text():
            assert p.poll() is None and time.monotonic() < end, (tmp_path / "robot.log").read_text()
            time.sleep(0.05)
        o = subprocess.run(["ip", "netns", "exec", op, sys.executable, str(REPO / "interop" / "ros2_operator.py"),
                            "--domain", str(domain), "--seconds", "4"], capture_output=True, text=True, timeout=90)
        assert o.returncode == 0, o.stdout + o.stderr[-3000:]
        r = json.loads(o.stdout.strip().splitlines()[-1])
        lat, gap = r["odom_latency_ms"], r["odom_interval_ms"]
        print(f"\ntwo hosts over veth: discovery {r['discovery_s']:.3f} s; first cmd_vel → first odom showing motion "
              f"{r['first_motion_s'] * 1e3:.1f} ms; odom intervals p50 {gap['p50']:.1f} ms, p99 {gap['p99']:.1f} ms, "
              f"max {gap['max']:.1f} ms; odom stamp → receipt p50 {lat['p50']:.1f} ms, p99 {lat['p99']:.1f} ms "
              f"over {r['odom_received']} messages; ~/stop answered in {r['stop_reply_ms']:.1f} ms")
        (REPO / "target").mkdir(exist_ok=True)
        (REPO / "target" / "ros2-two-hosts.json").write_text(json.dumps(r, indent=1))
        assert r["first_motion_s"] is not None, r
        assert r["stop_success"] and r["at_rest_after_stop"], r
        # 3 s (after the first second) at 50 Hz.
        assert r["odom_received"] >= 140, r
        assert r["final_x"] > 0.1, r
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=5)
        log.close()
    assert p.returncode == 0, (tmp_path / "robot.log").read_text()[-3000:]
    summary = json.loads((tmp_path / "robot.json").read_text())
    assert summary["fault_reason"] is None and summary["supervisor_final_state"] == "stopped", summary
