"""rollbase checked by the CAN tools engineers already use: python-can (socketcand client,
candump log reader/writer), cantools (DBC), the mcap reader (with CRC validation). None of them was written for
rollbase; each test asserts what the tool saw."""

import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import can
import pytest
from mcap.reader import make_reader

from conftest import REPO, binary, crc8_j1850, frame_crc_ok, rollbase, with_crc

SYNC_ID = 0x080
NODES = (1, 2, 3, 4)


def test_crc_reference_value():
    # The check value the protocol document gives for CRC-8 SAE J1850.
    assert crc8_j1850(b"123456789") == 0x4B


def documented_topics():
    """TOPICS as declared in src/record.rs (the documented list of per-cycle topics)."""
    src = (REPO / "src" / "record.rs").read_text()
    block = re.search(r"pub const TOPICS: \[&str; \d+\] = \[(.*?)\];", src, re.S)
    assert block, "TOPICS not found in src/record.rs"
    topics = re.findall(r'"([^"]+)"', block.group(1))
    assert len(topics) == 10, topics
    return topics


def half_step(signal) -> float:
    return abs(signal.scale) / 2.0


def demo(tmp_path: Path, scenario: str):
    """`rollbase demo --lockstep` writing a candump log and a recording; returns
    (summary JSON, log path, mcap path)."""
    log = tmp_path / f"{scenario}.log"
    rec = tmp_path / f"{scenario}.mcap"
    out = rollbase(
        "demo", "--lockstep", "--scenario", scenario, "--json",
        "--candump", str(log), "--record", str(rec),
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout), log, rec


def monitor_json(log: Path):
    """Our decoder's view of a candump log: one JSON object per line, then the summary."""
    out = rollbase("monitor", "--candump", str(log), "--json", "--summary")
    assert out.returncode == 0, out.stderr
    rows = [json.loads(line) for line in out.stdout.splitlines()]
    assert rows and "summary" in rows[-1], out.stdout[-500:]
    return rows[:-1], rows[-1]["summary"]


# --------------------------------------------------------------------------------------
# cantools: the DBC and a demo capture, signal for signal
# --------------------------------------------------------------------------------------


def test_cantools_decodes_every_frame_of_a_demo_capture_like_our_decoder(tmp_path, dbc_db):
    _, log, _ = demo(tmp_path, "seed000")
    ours, summary = monitor_json(log)
    assert summary["unparsable_lines"] == 0 and summary["rejected"] == 0, summary
    lines = log.read_text().splitlines()
    assert len(ours) == len(lines) > 10_000
    kinds = set()
    for n, row in enumerate(ours):
        assert row["accepted"], f"line {n + 1}: {row}"
        data = bytes.fromhex(row["data"])
        msg = dbc_db.get_message_by_frame_id(row["id"])
        assert msg.length == row["dlc"] == len(data), f"line {n + 1}: DLC"
        assert msg.name.startswith(row["message"]), (msg.name, row["message"])
        decoded = msg.decode(data, decode_choices=False)
        assert set(decoded) == set(row["signals"]), (msg.name, decoded, row["signals"])
        for name, value in decoded.items():
            sig = msg.get_signal_by_name(name)
            tol = half_step(sig) + 1e-9
            assert abs(float(value) - float(row["signals"][name])) <= tol, (
                f"line {n + 1} {msg.name}.{name}: cantools {value}, rollbase {row['signals'][name]}"
            )
        assert frame_crc_ok(row["id"], data), f"line {n + 1}: CRC"
        kinds.add(row["message"])
    assert kinds == {"SYNC", "SETPOINT", "FEEDBACK_A", "FEEDBACK_B", "STATUS"}


# --------------------------------------------------------------------------------------
# python-can's log reader and writer
# --------------------------------------------------------------------------------------


def test_python_can_reads_our_candump_log_frame_for_frame(tmp_path):
    _, log, _ = demo(tmp_path, "seed001")
    pattern = re.compile(r"^\((\d+)\.(\d{6})\) (\S+) ([0-9A-F]{3})#([0-9A-F]*)$")
    expected = []
    for line in log.read_text().splitlines():
        m = pattern.match(line)
        assert m, f"not candump -L format: {line!r}"
        expected.append((int(m.group(1)) + int(m.group(2)) * 1e-6, m.group(3), int(m.group(4), 16), bytes.fromhex(m.group(5))))
    got = list(can.CanutilsLogReader(str(log)))
    assert len(got) == len(expected) > 10_000
    for n, (msg, (t, chan, can_id, data)) in enumerate(zip(got, expected)):
        assert (msg.arbitration_id, bytes(msg.data), msg.dlc) == (can_id, data, len(data)), f"line {n + 1}"
        assert not msg.is_extended_id and not msg.is_remote_frame and not msg.is_error_frame
        assert msg.channel == chan == "vcan0"
        assert abs(msg.timestamp - t) < 1e-6, f"line {n + 1}"
    # can.LogReader picks the same reader from the .log extension.
    assert sum(1 for _ in can.LogReader(str(log))) == len(expected)


def test_our_reader_reads_a_log_written_by_python_can(tmp_path):
    _, log, _ = demo(tmp_path, "seed000")
    msgs = list(can.CanutilsLogReader(str(log)))[:5000]
    written = tmp_path / "python-can.log"
    with can.CanutilsLogWriter(str(written), channel="vcan0") as w:
        for m in msgs:
            w.on_message_received(m)
    text = written.read_text().splitlines()
    assert len(text) == len(msgs)
    # python-can appends the direction flag (" R"): our reader must take it.
    assert text[0].endswith(" R"), text[0]
    ours, summary = monitor_json(written)
    assert summary["unparsable_lines"] == 0, summary
    assert summary["frames"] == len(msgs) and summary["rejected"] == 0, summary
    for n, (row, m) in enumerate(zip(ours, msgs)):
        assert row["id"] == m.arbitration_id and bytes.fromhex(row["data"]) == bytes(m.data), f"line {n + 1}"
        assert abs(row["t"] - m.timestamp) < 2e-6, f"line {n + 1}"
        assert row["accepted"], f"line {n + 1}: {row}"


# --------------------------------------------------------------------------------------
# mcap: every recording the demo writes
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("scenario", ["seed000", "seed001"])
def test_mcap_reader_opens_demo_recordings_and_counts_match(tmp_path, scenario):
    summary_json, _, rec = demo(tmp_path, scenario)
    expected = summary_json["recorded_messages"]
    topics = documented_topics()
    # Every recording also carries the ROS 2 node's state topics (from the state port, at the
    # node's default rates; src/record.rs); a trajectory run takes no commands (no cmd_vel).
    state_topics = {"/odom", "/tf", "/joint_states", "/diagnostics", "/supervisor_state"}
    # Topics without messages (no rejected frame in a clean run) have no channel.
    assert set(expected) <= set(topics) | state_topics, expected
    assert (set(topics) | state_topics) - set(expected) <= {"/can/rejected"}, expected
    with open(rec, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None, "no summary section"
        chans = {c.topic: c for c in summary.channels.values()}
        assert sorted(chans) == sorted(expected)
        for topic, ch in chans.items():
            schema = summary.schemas[ch.schema_id]
            assert ch.message_encoding == "cdr", topic
            assert schema.encoding == "ros2msg", topic
            assert "/msg/" in schema.name, (topic, schema.name)
        counts = {t: 0 for t in expected}
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] += 1
            assert message.data[:4] == b"\x00\x01\x00\x00", channel.topic  # CDR_LE
    assert counts == expected
    assert all(n > 0 for n in counts.values()), counts
    stats = summary.statistics
    assert stats.message_count == sum(expected.values())
    assert {chans_topic: stats.channel_message_counts[c.id] for chans_topic, c in chans.items()} == expected


# --------------------------------------------------------------------------------------
# socketcand: python-can on our bridge, during a real-time run and as a controller
# --------------------------------------------------------------------------------------


def connect(host: str, port: int) -> can.BusABC:
    # tcp_tune: TCP_NODELAY + TCP_QUICKACK. Without it Nagle and delayed ACKs hold small
    # writes back for ~40 ms, longer than a cycle and close to the modules' 50 ms watchdog.
    return can.Bus(interface="socketcand", host=host, port=port, channel="vcan0", tcp_tune=True)


def socketcand_realtime_attempt(tmp_path, procs, host, port, k):
    """One real-time run of seed 000 over our bridge with python-can listening: a fresh
    simulator, then `rollbase run`; returns (exit code, stdout, stderr, frames python-can saw,
    the capture it wrote, the run's recording, the simulator's stderr after its clean stop)."""
    url = f"socketcand://{host}:{port}/vcan0"
    sim = procs([binary("rollbase-sim"), "--bus", url, "--start", "scenario:seed000"], tmp_path / f"sim{k}.log")
    sim.wait_for("waiting for SYNC")
    bus = connect(host, port)
    captured = tmp_path / f"python-can-capture{k}.log"
    writer = can.CanutilsLogWriter(str(captured), channel="vcan0")
    rec = tmp_path / f"run{k}.mcap"
    run = subprocess.Popen(
        [str(binary("rollbase")), "run", "--bus", url, "--trajectory", "scenario:seed000",
         "--duration", "5", "--json", "--record", str(rec)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    msgs = []
    try:
        deadline = time.monotonic() + 60
        while run.poll() is None and time.monotonic() < deadline:
            m = bus.recv(timeout=0.1)
            if m is not None:
                msgs.append(m)
                writer.on_message_received(m)
        out, err = run.communicate(timeout=30)
    finally:
        if run.poll() is None:
            run.kill()
        writer.stop()
        bus.shutdown()
        sim_text = sim.stop()
    return run.returncode, out, err, msgs, captured, rec, sim_text


def stale_feedback_fault(out: str) -> str | None:
    """The fault reason of a `--json` summary when it is a stale-feedback fault, else None."""
    try:
        reason = json.loads(out).get("fault_reason") or ""
    except ValueError:
        return None
    return reason if reason.startswith("stale feedback") else None


def test_python_can_socketcand_client_sees_a_realtime_run(tmp_path, procs, bridge, dbc_db):
    host, port, _ = bridge
    code, out, err, msgs, captured, rec, sim_text = socketcand_realtime_attempt(tmp_path, procs, host, port, 1)
    # A host stall (a loaded CI machine: cycles 8.9 ms apart at p99) can hold the feedback back
    # for more than the supervisor's stale limit, and the run then rightly stops in a fault.
    # Only that fault earns one more run on a fresh simulator, as the real-time CLI tests and
    # scripts/readme-socketcand.sh do; both summaries are printed if the second fails too.
    first = out
    if code == 1 and (reason := stale_feedback_fault(out)) is not None:
        print(f"first run ended in a fault: {reason}; one more run")
        code, out, err, msgs, captured, rec, sim_text = socketcand_realtime_attempt(tmp_path, procs, host, port, 2)
    # With --json the reason a run ended in a fault is in its summary on stdout, not on stderr.
    assert code == 0, f"exit {code}; stderr: {err!r}; summary: {out[-2000:]}; first run: {first[-600:]}"
    result = json.loads(out)
    assert result["supervisor_final_state"] == "stopped", result
    assert result["rejected_frames"] == 0, result
    cycles = result["cycles"]
    assert cycles >= 1000, result  # 5 s at 250 Hz
    by_id = {}
    for m in msgs:
        assert not m.is_extended_id
        by_id.setdefault(m.arbitration_id, []).append(m)
        # Every frame: known to the DBC, right DLC, CRC correct, decodable by cantools.
        spec = dbc_db.get_message_by_frame_id(m.arbitration_id)
        assert m.dlc == spec.length, hex(m.arbitration_id)
        assert frame_crc_ok(m.arbitration_id, bytes(m.data)), hex(m.arbitration_id)
        spec.decode(bytes(m.data))
    syncs = by_id.get(SYNC_ID, [])
    # python-can joined before the run started, so it saw (nearly) every cycle.
    assert len(syncs) >= 0.95 * cycles, (len(syncs), cycles)
    for n in NODES:
        for base in (0x180, 0x280, 0x200):
            assert len(by_id.get(base + n, [])) >= 0.95 * cycles, (hex(base + n), cycles)
    cycles_seen = [dbc_db.decode_message(SYNC_ID, bytes(m.data))["cycle"] for m in syncs]
    assert all((b - a) % 65536 == 1 for a, b in zip(cycles_seen, cycles_seen[1:]))
    # Our own decoder accepts the capture python-can wrote (CRCs, counters, ranges).
    ours, summary = monitor_json(captured)
    assert summary["frames"] == len(msgs) and summary["rejected"] == 0, summary
    assert summary["accepted"]["SYNC"] == len(syncs)
    # The run's recording matches its summary too.
    with open(rec, "rb") as f:
        stats = make_reader(f).get_summary().statistics
    assert stats.message_count == sum(result["recorded_messages"].values())
    assert re.search(r"node 1: \w+, \d+ SYNCs answered, \d+ setpoints ok, 0 bad CRC, 0 bad counter", sim_text), sim_text


# The modules' setpoint watchdog (50 ms) trips when this test's own 250 Hz loop stalls (a
# loaded 2-core CI host starves python or the bridge): that is the simulator doing its job,
# not a failed acceptance. An attempt whose send loop or reply stream had a gap longer than
# STALL_S is discarded and the experiment repeated; the assertions hold for the first clean one.
STALL_S = 0.040
ATTEMPTS = 3


def _setpoint_experiment(tmp_path, procs, host, port, dbc_db, attempt):
    url = f"socketcand://{host}:{port}/vcan0"
    sim = procs([binary("rollbase-sim"), "--bus", url], tmp_path / f"sim{attempt}.log")
    sim.wait_for("waiting for SYNC")
    bus = connect(host, port)
    sync_msg = dbc_db.get_message_by_name("SYNC")
    sp1 = dbc_db.get_message_by_name("SETPOINT_1")
    sp2 = dbc_db.get_message_by_name("SETPOINT_2")
    r = {"target": 2.0, "cycles": 150, "sent_ok": 0, "sent_bad": 0, "speeds": [], "states": [],
         "send_gap": 0.0, "rx_gap": 0.0}
    bad_every = 10
    speeds, states = r["speeds"], r["states"]
    last_send = last_rx = None

    def frame(msg, values):
        raw = msg.encode({**values, "crc": 0})
        return can.Message(arbitration_id=msg.frame_id, data=with_crc(msg.frame_id, raw), is_extended_id=False)

    def got(m):
        nonlocal last_rx
        if m.arbitration_id == 0x181:
            now = time.monotonic()
            if last_rx is not None and now - last_rx > r["rx_gap"]:
                r["rx_gap"] = now - last_rx
                r["rx_gap_at"] = len(speeds)
            last_rx = now
            speeds.append(dbc_db.decode_message(0x181, bytes(m.data))["wheel_speed"])
        elif m.arbitration_id == 0x701:
            states.append(dbc_db.decode_message(0x701, bytes(m.data), decode_choices=False)["state"])

    try:
        t_next = time.monotonic()
        for k in range(r["cycles"]):
            now = time.monotonic()
            if last_send is not None:
                r["send_gap"] = max(r["send_gap"], now - last_send)
            last_send = now
            bus.send(frame(sync_msg, {"cycle": k, "counter": k % 16}))
            bus.send(frame(sp1, {"wheel_speed": r["target"], "steer_rate": 0.0, "enable": 1, "brake": 0,
                                 "fault_reset": 0, "counter": k % 16}))
            if k % bad_every == 0:
                bad = frame(sp2, {"wheel_speed": 1.0, "steer_rate": 0.0, "enable": 1, "brake": 0,
                                  "fault_reset": 0, "counter": (k // bad_every) % 16})
                bad.data[-1] ^= 0x5A  # wrong CRC: must be refused
                bus.send(bad)
                r["sent_bad"] += 1
            r["sent_ok"] += 1
            t_next += 0.004
            while True:
                m = bus.recv(timeout=max(0.0, t_next - time.monotonic()))
                if m is None:
                    break
                got(m)
        # Flush: the simulator counts a setpoint when the next SYNC closes its cycle, and
        # closing this socket with replies still unread makes the kernel reset the
        # connection, which can drop our last frames inside the bridge. So send one more
        # SYNC and wait for node 1's answer to it (replies come in order) before closing.
        bus.send(frame(sync_msg, {"cycle": r["cycles"], "counter": r["cycles"] % 16}))
        deadline = time.monotonic() + 2.0
        while len(speeds) < r["cycles"] + 1 and time.monotonic() < deadline:
            m = bus.recv(timeout=max(0.0, deadline - time.monotonic()))
            if m is not None:
                got(m)
    finally:
        bus.shutdown()
    r["text"] = sim.stop()
    return r


def test_setpoints_from_python_can_are_accepted_by_the_simulator(tmp_path, procs, bridge, dbc_db):
    host, port, _ = bridge
    stalled = []
    for attempt in range(ATTEMPTS):
        r = _setpoint_experiment(tmp_path, procs, host, port, dbc_db, attempt)
        print(f"attempt {attempt}: send gap {r['send_gap'] * 1e3:.1f} ms, reply gap {r['rx_gap'] * 1e3:.1f} ms")
        if max(r["send_gap"], r["rx_gap"]) <= STALL_S:
            break
        stalled.append(f"attempt {attempt}: send gap {r['send_gap'] * 1e3:.1f} ms, "
                       f"reply gap {r['rx_gap'] * 1e3:.1f} ms at reply {r.get('rx_gap_at')}")
    else:
        pytest.fail(f"every attempt's 250 Hz loop stalled longer than {STALL_S * 1e3:.0f} ms "
                    f"(host too loaded for this timing test): {stalled}")
    if stalled:
        print("discarded (test loop stalled):", stalled)
    text, speeds, states, cycles = r["text"], r["speeds"], r["states"], r["cycles"]
    assert len(speeds) == cycles + 1, (len(speeds), text)
    node = {int(n): (int(ok), int(crc), int(cnt)) for n, ok, crc, cnt in re.findall(
        r"node (\d): \w+, \d+ SYNCs answered, (\d+) setpoints ok, (\d+) bad CRC, (\d+) bad counter", text)}
    assert node[1] == (r["sent_ok"], 0, 0), text
    assert node[2] == (0, r["sent_bad"], 0), text
    assert re.search(r"node 1: Enabled, .* 0 watchdog trips", text), text
    # Behaviour: module 1 enabled (STATUS state 2) and its wheel reached the commanded speed.
    assert 2 in states, states
    assert abs(speeds[-1] - r["target"]) < 0.05, f"{speeds[-10:]} {states[-5:]}\n{text}"


def test_tshark_reads_our_candump_log_if_installed(tmp_path):
    tshark = shutil.which("tshark")
    if tshark is None:
        pytest.skip("tshark not installed (optional check)")
    _, log, _ = demo(tmp_path, "seed000")
    out = subprocess.run([tshark, "-r", str(log), "-c", "100", "-T", "fields", "-e", "can.id"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    ids = [int(x, 0) for x in out.stdout.split()]
    assert len(ids) == 100 and SYNC_ID in ids
