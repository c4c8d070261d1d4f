"""The ROS 2 node's memory after huge messages (issue 27, finding 8; issue 26): `rollbase demo
--ros2` receives samples of 32 MB (leg commands of 4 million entries, as in the review, and a
"Twist" of the same size from a broken or hostile publisher) from an independent DDS peer
(Cyclone DDS), reliable and best effort, then a normal stream. The vendored rustdds
(vendor/rustdds/PATCHES.md) drops a fragmented sample announcing more than 256 KiB before
allocating it and reports it; the node counts it per endpoint (`oversized samples dropped` in
its summary line). And a burst of samples under that cap that lose fragments on the loopback
(best effort: never repaired). After each, the process's resident memory must be back near
where it was: before the fixes, 55.9 → 109 MB for good in the review (glibc's malloc kept the
freed 32 MB blocks), then +93.9 MB with a best-effort leg reader (rustdds kept a reassembly
buffer per huge sample that lost a fragment) (docs/ros2.md, Memory).

DDS discovery multicasts: runs only inside a private network namespace with only loopback
(.ci/run: `unshare -n sh -c 'ip link set lo up; …'`); skipped elsewhere
(ROLLBASE_REQUIRE_DDS=1: fails instead)."""

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

from conftest import binary

NETNS_HINT = "run inside a private network namespace: unshare -n sh -c 'ip link set lo up; python3 -m pytest interop/test_ros2_memory.py'"


def only_loopback() -> bool:
    try:
        with open("/proc/net/dev") as f:
            lines = f.read().splitlines()[2:]
    except OSError:
        return False
    return {line.split(":", 1)[0].strip() for line in lines if ":" in line} == {"lo"}


if os.environ.get("ROLLBASE_REQUIRE_DDS") == "1" and not only_loopback():
    raise RuntimeError(f"ROLLBASE_REQUIRE_DDS=1 but this is not a loopback-only network namespace: {NETNS_HINT}")

pytestmark = pytest.mark.skipif(not only_loopback(), reason=f"DDS test outside a private network namespace: {NETNS_HINT}")

if only_loopback():
    from dataclasses import dataclass, field

    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import float64, sequence
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    import ros2_types as rt

    RELIABLE = Qos(
        Policy.Reliability.Reliable(duration(seconds=10)),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(10),
    )
    BEST_EFFORT = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(10))

    # A "Twist" as a broken or hostile publisher may send it: the type name of
    # geometry_msgs/Twist (DDS matches on names), any content.
    @dataclass
    class HugeTwist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
        data: sequence[float64] = field(default_factory=list)

HUGE = 4_000_000  # entries (f64): 32 MB, the review's message
HUGE_COUNT = 3
# Under rustdds's cap (256 KiB): 30 000 entries, 240 kB, sent best effort by a lossy peer; the
# ones that complete reach the node and the command port refuses them.
UNDER_CAP = 30_000
UNDER_CAP_COUNT = 100
# Cyclone DDS drops this share of the datagrams it sends (per mille; its Internal/Test/
# XmitLossiness setting, for tests): a 240 kB sample is about 20 datagrams, so most lose a
# fragment, which best effort never repairs.
LOSSINESS = 100
# The node's command readers keep up to the last 10 samples (ResourceLimits; rustdds's default
# is 64): a normal stream longer than that replaces whatever came before.
NORMAL_COUNT = 80
# What may stay: the node's normal growth over the test (a few hundred kB) and allocator
# slack. The huge messages were 96 MB; before the fixes 14–94 MB of them stayed.
MAX_GROWTH_KB = 4 * 1024
DOMAIN = 41


def rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return int(re.search(r"VmRSS:\s+(\d+)", f.read()).group(1))


def oversized_counts(log: str) -> dict:
    """The node's summary line: `oversized samples dropped {"/leg_commands": 3}`."""
    m = re.search(r"oversized samples dropped \{([^}]*)\}", log)
    assert m, "no node summary line in the log"
    return {k: int(v) for k, v in re.findall(r'"([^"]+)": (\d+)', m.group(1))}


def commands_passed(log: str) -> int:
    """The node's summary line: `ROS 2 node: N commands passed on`."""
    m = re.search(r"ROS 2 node: (\d+) commands passed on", log)
    assert m, "no node summary line in the log"
    return int(m.group(1))


def run_demo(tmp_path: Path, send, domain=DOMAIN):
    """Runs `demo --ros2`; `send(dp)` publishes the test's samples and returns the normal
    stream's writer and sample; returns (VmRSS before, at the peak, after, log, summary)."""
    log = tmp_path / "demo.log"
    out = tmp_path / "demo.json"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), RUST_LOG="info")
    with open(out, "w") as o, open(log, "w") as e:
        p = subprocess.Popen([str(binary("rollbase")), "demo", "--ros2", "--json"], stdout=o, stderr=e, env=env)
    try:
        end = time.monotonic() + 30
        while "state: tracking" not in log.read_text():
            assert p.poll() is None and time.monotonic() < end, log.read_text()
            time.sleep(0.05)
        dp = DomainParticipant(domain)
        before = None

        def settled():
            nonlocal before
            # Discovery, then the node's working set settles.
            time.sleep(3)
            before = rss_kb(p.pid)

        normal_w, normal = send(dp, settled)
        peak = rss_kb(p.pid)
        for _ in range(NORMAL_COUNT):
            normal_w.write(normal)
            time.sleep(0.05)
        # rustdds re-allocates what it keeps after 5 s (releasing its receive buffers).
        time.sleep(8)
        after = rss_kb(p.pid)
        print(f"VmRSS before {before} kB, after the big samples {peak} kB, after the normal stream {after} kB")
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=30) in (0, 1), log.read_text()  # 1: a fault (the machine's load)
        return before, peak, after, log.read_text(), json.loads(out.read_text())
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=10)


@pytest.mark.parametrize("reliability", ["reliable", "best_effort"])
def test_huge_leg_commands_are_dropped_unallocated_and_counted(tmp_path: Path, reliability):
    qos = RELIABLE if reliability == "reliable" else BEST_EFFORT

    def send(dp, settled):
        legs = DataWriter(dp, Topic(dp, "rt/leg_commands", rt.Float64MultiArray, qos=qos), qos=qos)
        settled()
        huge = rt.Float64MultiArray(data=[0.45] * HUGE)
        for _ in range(HUGE_COUNT):
            legs.write(huge)
            time.sleep(2)
        return legs, rt.Float64MultiArray(data=[0.45] * 4)

    before, peak, after, log, summary = run_demo(tmp_path, send)
    assert after - before <= MAX_GROWTH_KB, f"{after - before} kB stayed after {HUGE_COUNT} leg commands of 32 MB"
    # Never allocated: the peak stays far below one 32 MB sample.
    assert peak - before <= MAX_GROWTH_KB, f"+{peak - before} kB at the peak"
    # Each huge sample dropped and counted once (its fragments lost on the loopback or not).
    assert oversized_counts(log) == {"/leg_commands": HUGE_COUNT}, log[-3000:]
    assert "/leg_commands: a publisher sent a sample larger than 256 KiB" in log
    # The normal stream after them arrived and nothing was refused: from the reliable writer
    # every sample (it was not held up behind the dropped ones, which the reader acknowledged
    # as irrelevant); best effort may lose one in principle.
    passed = commands_passed(log)
    if reliability == "reliable":
        assert passed == NORMAL_COUNT, log[-3000:]
    else:
        assert 1 <= passed <= NORMAL_COUNT, log[-3000:]
    assert summary["rejected_commands"] == 0, summary


def test_a_huge_sample_on_cmd_vel_is_dropped_unallocated_and_counted(tmp_path: Path):
    """The best-effort cmd_vel reader with a 32 MB "Twist" (a Twist is 48 bytes)."""

    def send(dp, settled):
        topic = Topic(dp, "rt/cmd_vel", HugeTwist, qos=BEST_EFFORT)
        w = DataWriter(dp, topic, qos=BEST_EFFORT)
        settled()
        huge = HugeTwist(data=[0.0] * HUGE)
        for _ in range(HUGE_COUNT):
            w.write(huge)
            time.sleep(2)
        # The normal stream: a Twist of the real type on the same topic.
        tw = DataWriter(dp, Topic(dp, "rt/cmd_vel", rt.Twist, qos=BEST_EFFORT), qos=BEST_EFFORT)
        time.sleep(1)
        return tw, rt.Twist()

    before, peak, after, log, _ = run_demo(tmp_path, send)
    assert after - before <= MAX_GROWTH_KB, f"{after - before} kB stayed after {HUGE_COUNT} samples of 32 MB"
    assert peak - before <= MAX_GROWTH_KB, f"+{peak - before} kB at the peak"
    assert oversized_counts(log) == {"/cmd_vel": HUGE_COUNT}, log[-3000:]


def test_samples_under_the_cap_that_lose_fragments_leave_nothing(tmp_path: Path, monkeypatch):
    """Best-effort 240 kB leg commands (under the cap) from a peer that loses 10 % of its
    datagrams: most lose a fragment (never repaired: their partial reassemblies stay until
    rustdds evicts them), the others complete and the command port refuses them."""
    # A domain of its own: Cyclone reads its configuration when it creates a domain.
    domain = DOMAIN + 2
    monkeypatch.setenv(
        "CYCLONEDDS_URI",
        f"<CycloneDDS><Domain id='{domain}'><Internal><Test><XmitLossiness>{LOSSINESS}</XmitLossiness></Test></Internal></Domain></CycloneDDS>",
    )

    def send(dp, settled):
        legs = DataWriter(dp, Topic(dp, "rt/leg_commands", rt.Float64MultiArray, qos=BEST_EFFORT), qos=BEST_EFFORT)
        end = time.monotonic() + 20
        while not legs.get_matched_subscriptions():
            assert time.monotonic() < end, "the node's leg reader did not match"
            time.sleep(0.05)
        settled()
        big = rt.Float64MultiArray(data=[0.45] * UNDER_CAP)
        for _ in range(UNDER_CAP_COUNT):
            legs.write(big)
        time.sleep(2)
        return legs, rt.Float64MultiArray(data=[0.45] * 4)

    before, peak, after, log, summary = run_demo(tmp_path, send, domain)
    completed = summary["rejected_commands"]
    print(f"{completed} of {UNDER_CAP_COUNT} completed and were refused by the command port")
    assert after - before <= MAX_GROWTH_KB, f"{after - before} kB stayed after {UNDER_CAP_COUNT} samples of 240 kB"
    assert oversized_counts(log) == {}, log[-3000:]
    # Fragments were lost (what this test is about), and samples under the cap still arrive.
    assert 1 <= completed < UNDER_CAP_COUNT, summary
