"""The operator's side of the two-host test (interop/test_ros2_fleet.py): an Eclipse Cyclone DDS
peer that runs in its own network namespace (the "operator" host), finds rollbase's node on
the "robot" host across a veth link by multicast discovery, drives it with cmd_vel, watches
odom and calls ~/stop. Prints one JSON object with what it measured.

Usage: python3 ros2_operator.py --domain D [--ns /robot1] [--seconds 4]"""

import argparse
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cyclonedds.core import Policy, Qos  # noqa: E402
from cyclonedds.domain import DomainParticipant  # noqa: E402
from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402
from cyclonedds.util import duration  # noqa: E402

import ros2_types as rt  # noqa: E402

QOS = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.Durability.Volatile, Policy.History.KeepLast(10))
READER_QOS = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.Durability.Volatile, Policy.History.KeepLast(1000))
REST = 0.002  # m/s or rad/s: the base counts as at rest below this (10× the odometry's noise)


def pct(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))] if xs else None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--domain", type=int, required=True)
    ap.add_argument("--ns", default="")
    ap.add_argument("--seconds", type=float, default=4.0)
    a = ap.parse_args()
    ns = "" if a.ns in ("", "/") else a.ns
    out = {}
    t0 = time.monotonic()
    dp = DomainParticipant(a.domain)
    odom = DataReader(dp, Topic(dp, f"rt{ns}/odom", rt.Odometry, qos=QOS), qos=READER_QOS)
    cmd = DataWriter(dp, Topic(dp, f"rt{ns}/cmd_vel", rt.Twist, qos=QOS), qos=QOS)
    req = DataWriter(dp, Topic(dp, f"rq{ns}/rollbase/stopRequest", rt.TriggerRequest, qos=QOS), qos=QOS)
    rep = DataReader(dp, Topic(dp, f"rr{ns}/rollbase/stopReply", rt.TriggerResponse, qos=QOS), qos=QOS)
    while not (odom.get_matched_publications() and cmd.get_matched_subscriptions()
               and req.get_matched_subscriptions() and rep.get_matched_publications()):
        if time.monotonic() - t0 > 30:
            print(json.dumps({"error": "discovery across the link did not match in 30 s"}))
            return 1
        time.sleep(0.005)
    out["discovery_s"] = time.monotonic() - t0
    time.sleep(0.3)
    # Odometry across the link: the arrival intervals (50 Hz: 20 ms), and receipt − stamp.
    # The stamp is the robot's cycle time on its wall clock, the same kernel clock as ours
    # (two namespaces of one machine), so the difference is the delay through the node and
    # the link plus any offset of the stamps themselves; samples of the first second are left
    # out (a newly matched reader also receives the writer's last few samples).
    lat = []
    arrivals = []
    moving_at = None
    t_cmd = time.monotonic()
    end = t_cmd + a.seconds
    next_cmd = t_cmd
    sent = 0
    while time.monotonic() < end:
        if time.monotonic() >= next_cmd:
            cmd.write(rt.Twist(linear=rt.Vector3(x=0.2)))
            sent += 1
            next_cmd += 0.05
        for s in odom.take(N=100):
            if not isinstance(s, rt.Odometry):
                continue
            now = time.time()
            if time.monotonic() - t_cmd > 1.0:
                lat.append(now - (s.header.stamp.sec + s.header.stamp.nanosec * 1e-9))
                arrivals.append(time.monotonic())
            if moving_at is None and s.twist.twist.linear.x > REST:
                moving_at = time.monotonic() - t_cmd
        time.sleep(0.002)
    out["cmd_vel_sent"] = sent
    out["odom_received"] = len(lat)
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
    out["odom_interval_ms"] = {"p50": pct(gaps, 0.5) * 1e3, "p99": pct(gaps, 0.99) * 1e3, "max": max(gaps) * 1e3} if gaps else None
    out["first_motion_s"] = moving_at
    out["odom_latency_ms"] = {"p50": pct(lat, 0.5) * 1e3, "p99": pct(lat, 0.99) * 1e3, "max": max(lat) * 1e3} if lat else None
    # ~/stop across the link.
    t = time.monotonic()
    req.write(rt.TriggerRequest(client_guid=0x55, sequence_number=1))
    reply = None
    while reply is None and time.monotonic() - t < 10:
        for s in rep.take(N=10):
            if isinstance(s, rt.TriggerResponse) and (s.client_guid, s.sequence_number) == (0x55, 1):
                reply = s
        time.sleep(0.002)
    out["stop_reply_ms"] = (time.monotonic() - t) * 1e3 if reply else None
    out["stop_success"] = bool(reply and reply.success)
    # At rest after the stop (the halt takes well under 2 s at 0.2 m/s).
    t = time.monotonic()
    last = None
    while time.monotonic() - t < 3:
        for s in odom.take(N=100):
            if isinstance(s, rt.Odometry):
                last = s
        time.sleep(0.01)
    out["at_rest_after_stop"] = bool(last and max(abs(last.twist.twist.linear.x), abs(last.twist.twist.linear.y),
                                                  abs(last.twist.twist.angular.z)) < REST)
    out["final_x"] = last.pose.pose.position.x if last else math.nan
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
