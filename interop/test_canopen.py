"""rollbase's simulated CiA 402 drives and CiA 406 encoders checked by python-canopen, an
independent CANopen implementation, acting as the master over the socketcand bridge:
NMT (reset, boot-up, start), expedited SDO reads and writes with their abort codes, PDO
mapping written by SDO, SYNC-driven TPDOs, the CiA 402 state machine driven by controlword
writes, heartbeat production and consumption, and EMCY.

None of the master side here is rollbase code: frames are built and parsed by python-canopen
(SDO, NMT, EMCY) or by hand from CiA 301 (PDO payloads)."""

import math
import struct
import threading
import time

import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError

from conftest import binary

DRIVES = (1, 2, 3, 4, 5, 6, 7, 8)
ENCODERS = (9, 10, 11, 12)
MASTER = 0x7E  # python-canopen's heartbeat node-ID in the consumer test

STATE_MASKS = [  # (mask, value, name) of the CiA 402 statusword
    (0x4F, 0x40, "switch on disabled"),
    (0x6F, 0x21, "ready to switch on"),
    (0x6F, 0x23, "switched on"),
    (0x6F, 0x27, "operation enabled"),
    (0x4F, 0x08, "fault"),
    (0x4F, 0x0F, "fault reaction active"),
]


def state_of(sw: int) -> str:
    for mask, value, name in STATE_MASKS:
        if sw & mask == value:
            return name
    return f"other 0x{sw:04X}"


class Frames:
    """Raw frames of some COB-IDs, as python-canopen's network receives them."""

    def __init__(self, net, ids):
        self.lock = threading.Lock()
        self.got = {i: [] for i in ids}
        for i in ids:
            net.subscribe(i, self._cb)

    def _cb(self, can_id, data, timestamp):
        with self.lock:
            self.got[can_id].append(bytes(data))

    def take(self, can_id):
        with self.lock:
            out, self.got[can_id] = self.got[can_id], []
        return out


@pytest.fixture
def network(procs, bridge, tmp_path):
    """rollbase-sim with the CiA 402 profile on the bridge, and python-canopen's network on
    the same channel, every device reset and booted again (boot-up seen by python-canopen)."""
    host, port, _ = bridge
    sim = procs(
        [binary("rollbase-sim"), "--bus", f"socketcand://{host}:{port}/vcan0", "--profile", "cia402"],
        tmp_path / "sim.log",
    )
    sim.wait_for(r"Ctrl-C to stop")
    net = canopen.Network()
    net.connect(interface="socketcand", host=host, port=port, channel="vcan0", tcp_tune=True)
    nodes = {}
    for n in DRIVES + ENCODERS:
        node = canopen.RemoteNode(n, canopen.ObjectDictionary())
        node.sdo.RESPONSE_TIMEOUT = 1.0
        net.add_node(node)
        nodes[n] = node
    # Reset communication: each device answers with its boot-up message. (Collected by a
    # subscription made before the reset: python-canopen's wait_for_bootup() starts waiting
    # after the command and misses a device that answers within a millisecond.)
    boot = Frames(net, [0x700 + n for n in nodes])
    for node in nodes.values():
        node.nmt.send_command(0x82)
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and not all(boot.got[0x700 + n] for n in nodes):
        time.sleep(0.01)
    for n, node in nodes.items():
        assert bytes([0]) in boot.take(0x700 + n), f"no boot-up from node {n}"
        assert node.nmt.state == "PRE-OPERATIONAL", (n, node.nmt.state)
    yield net, nodes, sim
    net.disconnect()


def u32(b: bytes) -> int:
    assert len(b) == 4, b
    return struct.unpack("<I", b)[0]


def test_device_types_and_identity(network):
    _, nodes, _ = network
    for n in DRIVES:
        # CiA 301: low word = profile 402, high word 2 = servo drive.
        assert u32(nodes[n].sdo.upload(0x1000, 0)) == 0x0002_0192, n
    for n in ENCODERS:
        # Profile 406, encoder type 8 = absolute linear.
        assert u32(nodes[n].sdo.upload(0x1000, 0)) == 0x0008_0196, n
        # The measuring step the default platform file expects (1000 nm).
        assert u32(nodes[n].sdo.upload(0x6005, 1)) == 1000, n
    assert nodes[1].sdo.upload(0x1018, 0) == bytes([4])


@pytest.mark.parametrize(
    "action, code",
    [
        (lambda d: d.sdo.upload(0x1234, 0), 0x0602_0000),  # object does not exist
        (lambda d: d.sdo.upload(0x6060, 5), 0x0609_0011),  # sub-index does not exist
        (lambda d: d.sdo.download(0x6041, 0, b"\x06\x00"), 0x0601_0002),  # statusword is read-only
        (lambda d: d.sdo.download(0x6060, 0, bytes([3])), 0x0609_0030),  # only CSV (9) is emulated
        (lambda d: d.sdo.download(0x1017, 0, b"\x64\x00\x00\x00"), 0x0607_0010),  # UNSIGNED16 written with 4 bytes
        (lambda d: d.sdo.download(0x6041, 0, b"\x06\x00", force_segment=True), 0x0601_0002),  # segmented, read-only
        # Mapping a valid PDO: TPDO1 is valid after the reset, its mapping is locked.
        (lambda d: d.sdo.download(0x1A00, 0, bytes([0])), 0x0800_0022),
    ],
)
def test_sdo_aborts_are_the_cia301_codes(network, action, code):
    _, nodes, _ = network
    with pytest.raises(SdoAbortedError) as e:
        action(nodes[1])
    assert e.value.code == code, f"got 0x{e.value.code:08X}, expected 0x{code:08X}"


def test_sdo_writes_are_read_back(network):
    _, nodes, _ = network
    d = nodes[3]
    d.sdo.download(0x6060, 0, bytes([9]))
    # The mode display follows the mode a few ms later, as CiA 402 lets it (the emulator is
    # a real drive's twin): read it until it does, for at most 100 ms.
    end = time.monotonic() + 0.1
    while d.sdo.upload(0x6061, 0) != bytes([9]) and time.monotonic() < end:
        time.sleep(0.002)
    assert d.sdo.upload(0x6061, 0) == bytes([9])
    d.sdo.download(0x1017, 0, struct.pack("<H", 250))
    assert d.sdo.upload(0x1017, 0) == struct.pack("<H", 250)
    d.sdo.download(0x1006, 0, struct.pack("<I", 4000))
    assert u32(d.sdo.upload(0x1006, 0)) == 4000


def map_tpdo1(node, entries, transmission=1):
    """TPDO1 remapped by SDO in the CiA 301 order: invalid, mapping, valid."""
    cob = 0x180 + node.id
    node.sdo.download(0x1800, 1, struct.pack("<I", 0xC000_0000 | cob))
    node.sdo.download(0x1800, 2, bytes([transmission]))
    node.sdo.download(0x1A00, 0, bytes([0]))
    for i, (index, sub, bits) in enumerate(entries, start=1):
        node.sdo.download(0x1A00, i, struct.pack("<I", (index << 16) | (sub << 8) | bits))
    node.sdo.download(0x1A00, 0, bytes([len(entries)]))
    node.sdo.download(0x1800, 1, struct.pack("<I", 0x4000_0000 | cob))


def test_pdo_mapping_by_sdo_and_sync_driven_tpdos(network):
    net, nodes, _ = network
    drive, enc = nodes[2], nodes[10]
    # A drive TPDO1 with statusword + velocity actual (6 bytes), an encoder TPDO1 with the
    # position value only (4 bytes): the devices must send what their dictionaries say.
    map_tpdo1(drive, [(0x6041, 0, 16), (0x606C, 0, 32)])
    map_tpdo1(enc, [(0x6004, 0, 32)], transmission=2)
    # Entries beyond 64 bits or of unmappable objects are refused when sub 0 is written.
    drive.sdo.download(0x1800, 1, struct.pack("<I", 0xC000_0182))
    drive.sdo.download(0x1A00, 0, bytes([0]))
    for i in range(1, 4):
        drive.sdo.download(0x1A00, i, struct.pack("<I", 0x6064_0020))
    with pytest.raises(SdoAbortedError) as e:
        drive.sdo.download(0x1A00, 0, bytes([3]))
    assert e.value.code == 0x0604_0042
    drive.sdo.download(0x1A00, 1, struct.pack("<I", 0x1000_0020))  # device type: not mappable
    with pytest.raises(SdoAbortedError) as e:
        drive.sdo.download(0x1A00, 0, bytes([1]))
    assert e.value.code == 0x0604_0041
    map_tpdo1(drive, [(0x6041, 0, 16), (0x606C, 0, 32)])

    frames = Frames(net, [0x182, 0x18A])
    for n in (2, 10):
        nodes[n].nmt.state = "OPERATIONAL"
    time.sleep(0.2)
    assert frames.take(0x182) == [] and frames.take(0x18A) == [], "no TPDO without SYNC"
    for _ in range(10):
        net.sync.transmit()
        time.sleep(0.01)
    time.sleep(0.1)
    d = frames.take(0x182)
    e = frames.take(0x18A)
    # Transmission type 1: every SYNC; type 2: every second SYNC.
    assert len(d) == 10, d
    assert len(e) == 5, e
    for payload in d:
        assert len(payload) == 6
        sw, vel = struct.unpack("<Hi", payload)
        assert state_of(sw) == "switch on disabled", hex(sw)
        # Standing still up to the simulated rate noise (σ = 2 mrad/s): below 10 mrad/s at
        # the joint, in the default steering units (16384 increments/rev, gear 50, inc/s).
        assert abs(vel) < 0.01 * 16384 * 50 / (2 * math.pi), vel
    for payload in e:
        assert len(payload) == 4
        # The simulated legs stand at their nominal 0.465 m: 465 000 steps of 1 µm, up to the
        # simulated leg noise (σ = 10 µm): within 6 σ.
        assert abs(struct.unpack("<I", payload)[0] - 465_000) <= 60, payload


def test_cia402_state_machine_and_velocity_following(network):
    net, nodes, _ = network
    d = nodes[1]  # wheel 1 rolling drive
    d.sdo.download(0x6060, 0, bytes([9]))
    d.nmt.state = "OPERATIONAL"
    seen = []
    for cw in (0x06, 0x07, 0x0F):
        d.sdo.download(0x6040, 0, struct.pack("<H", cw))
        seen.append(state_of(struct.unpack("<H", d.sdo.upload(0x6041, 0))[0]))
    assert seen == ["ready to switch on", "switched on", "operation enabled"]
    # 1 rad/s at the wheel = 16384 · 30 / 2π increments/s; the drive must follow it.
    target = round(16384 * 30 / (2 * math.pi))
    d.sdo.download(0x60FF, 0, struct.pack("<i", target))
    deadline = time.monotonic() + 3
    vel = 0
    while time.monotonic() < deadline:
        vel = struct.unpack("<i", d.sdo.upload(0x606C, 0))[0]
        if abs(vel - target) < 0.02 * target:
            break
        time.sleep(0.05)
    assert abs(vel - target) < 0.02 * target, (vel, target)
    # Disable voltage: the power stage is off and the wheel stops, to within the simulated
    # rate noise (σ = 2 mrad/s): below 10 mrad/s, 1 % of the speed it had.
    d.sdo.download(0x6040, 0, struct.pack("<H", 0x00))
    assert state_of(struct.unpack("<H", d.sdo.upload(0x6041, 0))[0]) == "switch on disabled"
    still = 0.01 * target
    deadline = time.monotonic() + 3
    while time.monotonic() < deadline:
        vel = struct.unpack("<i", d.sdo.upload(0x606C, 0))[0]
        if abs(vel) < still:
            break
        time.sleep(0.05)
    assert abs(vel) < still, (vel, still)


def test_heartbeat_producer_and_consumer_with_emcy(network):
    net, nodes, _ = network
    d = nodes[4]
    d.sdo.download(0x1017, 0, struct.pack("<H", 50))
    d.nmt.state = "OPERATIONAL"
    assert d.nmt.wait_for_heartbeat(timeout=2) == "OPERATIONAL"
    # The drive watches python-canopen's heartbeat (node 0x7E, 100 ms) and reacts to its loss
    # with EMCY 0x8130 and, being in operation enabled with 0x6007 = 1, a fault.
    d.sdo.download(0x1016, 1, struct.pack("<I", (MASTER << 16) | 100))
    d.sdo.download(0x6007, 0, struct.pack("<h", 1))
    d.sdo.download(0x6060, 0, bytes([9]))
    for cw in (0x06, 0x07, 0x0F):
        d.sdo.download(0x6040, 0, struct.pack("<H", cw))
    assert state_of(struct.unpack("<H", d.sdo.upload(0x6041, 0))[0]) == "operation enabled"
    for _ in range(10):
        net.send_message(0x700 + MASTER, bytes([0x05]))
        # The consumer's 100 ms run from the last heartbeat sent, not from after the sleep.
        t_last = time.monotonic()
        time.sleep(0.02)
    d.emcy.reset()
    err = d.emcy.wait(0x8130, timeout=2)
    waited = time.monotonic() - t_last
    assert err is not None and err.code == 0x8130, err
    assert 0.08 <= waited <= 0.5, waited
    assert state_of(struct.unpack("<H", d.sdo.upload(0x6041, 0))[0]) == "fault"
    # Fault reset (rising edge of bit 7): back to switch on disabled, EMCY "error reset".
    d.emcy.reset()
    d.sdo.download(0x6040, 0, struct.pack("<H", 0x00))
    d.sdo.download(0x6040, 0, struct.pack("<H", 0x80))
    assert state_of(struct.unpack("<H", d.sdo.upload(0x6041, 0))[0]) == "switch on disabled"
    # (Sent while the controlword download was answered: look in the log, wait() only sees
    # EMCYs that arrive after it is called.)
    deadline = time.monotonic() + 2
    while time.monotonic() < deadline and not any(e.code == 0 for e in d.emcy.log):
        time.sleep(0.01)
    assert [e.code for e in d.emcy.log] == [0x0000], d.emcy.log
    assert d.emcy.active == []


def test_nmt_stop_silences_sdo_and_pdo_until_started(network):
    net, nodes, _ = network
    d = nodes[11]
    d.nmt.state = "STOPPED"
    time.sleep(0.05)
    d.sdo.RESPONSE_TIMEOUT = 0.3
    with pytest.raises(canopen.SdoCommunicationError):
        d.sdo.upload(0x1000, 0)
    d.nmt.state = "PRE-OPERATIONAL"
    time.sleep(0.05)
    assert u32(d.sdo.upload(0x1000, 0)) == 0x0008_0196
