"""The ROS 2 node's memory after huge messages (issue 27, finding 8): `rollbase demo --ros2`
receives leg commands of 4 million entries (32 MB each; the command port refuses them, they
name 4 million legs) from an independent DDS peer (Cyclone DDS), then a normal stream of leg
commands. Once the huge samples have left rustdds's topic cache (the node's leg reader keeps
the last 10 samples; the normal stream replaces them), the process's resident memory must be
back near where it was: before the first fix glibc's malloc kept the freed 32 MB blocks (its
dynamic mmap threshold), 55.9 → 109 MB for good in the review; on the rustdds node before the
second, rustdds kept a reassembly buffer per huge sample that lost a fragment, +93.9 MB
(docs/ros2.md, Memory).

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
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    import ros2_types as rt

    QOS = Qos(
        Policy.Reliability.Reliable(duration(seconds=10)),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(10),
    )

HUGE = 4_000_000  # entries (f64): 32 MB, the review's message
HUGE_COUNT = 3
# rustdds keeps up to the last 10 samples of the leg topic (the node's ResourceLimits; its
# default is 64): a normal stream longer than that replaces the huge ones.
NORMAL_COUNT = 80
# What may stay: the node's normal growth over the test (a few hundred kB) and allocator
# slack. The huge messages were 96 MB; before the fix 14–50 MB of them stayed.
MAX_GROWTH_KB = 4 * 1024
DOMAIN = 41


def rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return int(re.search(r"VmRSS:\s+(\d+)", f.read()).group(1))


def test_huge_leg_commands_leave_no_memory_behind(tmp_path: Path):
    log = tmp_path / "demo.log"
    out = tmp_path / "demo.json"
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN), RUST_LOG="info")
    with open(out, "w") as o, open(log, "w") as e:
        p = subprocess.Popen([str(binary("rollbase")), "demo", "--ros2", "--json"], stdout=o, stderr=e, env=env)
    try:
        end = time.monotonic() + 30
        while "state: tracking" not in log.read_text():
            assert p.poll() is None and time.monotonic() < end, log.read_text()
            time.sleep(0.05)
        dp = DomainParticipant(DOMAIN)
        legs = DataWriter(dp, Topic(dp, "rt/leg_commands", rt.Float64MultiArray, qos=QOS), qos=QOS)
        # Discovery, then the node's working set settles.
        time.sleep(3)
        before = rss_kb(p.pid)
        huge = rt.Float64MultiArray(data=[0.45] * HUGE)
        for _ in range(HUGE_COUNT):
            legs.write(huge)
            time.sleep(2)
        peak = rss_kb(p.pid)
        for _ in range(NORMAL_COUNT):
            legs.write(rt.Float64MultiArray(data=[0.45] * 4))
            time.sleep(0.05)
        # rustdds re-allocates what it keeps after 5 s (releasing its receive buffers).
        time.sleep(8)
        after = rss_kb(p.pid)
        print(f"VmRSS before {before} kB, after the huge messages {peak} kB, after the normal stream {after} kB")
        assert after - before <= MAX_GROWTH_KB, f"{after - before} kB stayed after {HUGE_COUNT} messages of 32 MB"
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=30) in (0, 1), log.read_text()  # 1: a fault (the machine's load)
        summary = json.loads(out.read_text())
        # The huge messages reached the command port and were refused there (rustdds may give
        # up on a sample this large now and then: at least one must have come through).
        assert summary["rejected_commands"] >= 1, summary
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=10)
