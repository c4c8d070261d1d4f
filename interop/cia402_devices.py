"""An independent CiA 402 / CiA 406 device set for rollbase's interoperability tests:
4 rolling drives, 4 steering drives with incremental encoders and home switches, 4 linear
encoders, as python-canopen `LocalNode`s (SDO server, heartbeat, EMCY) with the EDS of
cia402_eds.py, on a socketcand bus. None of it is rollbase code: NMT, the PDOs configured by
SDO, SYNC, the CiA 402 state machine, homing mode 6 (methods 19/20 and 35/37) and the motor
model are written here from CiA 301 v4.2 and CiA 402 (IEC 61800-7-201).

Each drive integrates its own position from the velocity it is told (a first-order motor,
20 ms), so the platform moves as the devices' positions say. A steering drive's position
counter is 0 at power-on wherever its axis points (an incremental encoder); its home switch
is active over half a turn on the positive side of its edge (bit 2 of 0x60FD).

Run as a process: `python3 cia402_devices.py HOST PORT CHANNEL SEED`. Commands on stdin, one
per line: `emcy NODE CODE REGISTER` (register 0: a notice; else the drive faults with CODE in
0x603F and 0x1003), `powercycle NODE`, `state` (prints one JSON line), `debug` (the drives'
NMT state and PDO configuration as one JSON line), `quit`."""

import json
import math
import os
import random
import struct
import sys
import tempfile
import threading
import time

import canopen

from cia402_eds import write_eds

INCR = 16384  # encoder increments per motor revolution (0x608F:01)
GEAR = {"drive": 30.0, "steer": 50.0}
TAU_MOTOR = 0.02
EDGES = (0.3, -0.5, 1.0, -1.4)  # home switch edges of the four steering axes (rad)

# CiA 402 states and their statusword bits (0..3, 5, 6).
NRTSO, SOD, RTSO, SO, OE, QSA, FRA, FAULT = range(8)
STATE_BITS = {NRTSO: 0x00, SOD: 0x40, RTSO: 0x21, SO: 0x23, OE: 0x27, QSA: 0x07, FRA: 0x0F, FAULT: 0x08}


def u32(b):
    return struct.unpack("<I", bytes(b[:4]).ljust(4, b"\0"))[0]


class Device:
    def __init__(self, net, node, kind, role, wheel, eds_dir, steer_start=0.0):
        self.net, self.id, self.kind, self.role, self.wheel = net, node, kind, role, wheel
        path = write_eds(os.path.join(eds_dir, f"{node}.eds"), kind, node)
        self.od = canopen.import_od(path, node)
        self.node = canopen.LocalNode(node, self.od)
        net.add_node(self.node)
        self.lock = threading.Lock()
        self.gear = GEAR.get(role, 1.0)
        # Physical axis: angle (rad at the joint), rate.
        self.angle = steer_start
        self.rate = 0.0
        self.homings = 0
        self.mode_value = 0
        self.mode_display = 0
        self.target = 0
        self.node.add_read_callback(self.on_read)
        self.power_on()

    def on_read(self, index, subindex, od):
        """Process values come from the device's state, not the data store."""
        return self.value(index, subindex)

    def value(self, index, sub):
        if self.kind == "drive":
            if index == 0x6041:
                return self.statusword()
            if index == 0x6064:
                pos = round((self.angle - self.zero) * self.units_per_rad())
                return ((pos + 2**31) % 2**32) - 2**31
            if index == 0x606C:
                return int(round(self.rate * self.units_per_rad()))
            if index == 0x60FD:
                return 0x4 if self.switch() else 0
            if index == 0x6060:
                return self.mode_value
            if index == 0x6061:
                return self.mode_display
            if index == 0x6040:
                return self.cw
            if index == 0x60FF:
                return self.target
        elif index == 0x6004:
            return 465000  # the leg at 0.465 m, 1 µm steps
        elif index == 0x6030 and sub == 1:
            return 0
        return None

    # --- object access -------------------------------------------------------------
    def get(self, index, sub=0):
        v = self.od[index] if sub == 0 and not hasattr(self.od[index], "subindices") else self.od[index][sub]
        return v.decode_raw(self.node.get_data(index, sub))

    def put(self, index, sub, value):
        v = self.od[index] if sub == 0 and not hasattr(self.od[index], "subindices") else self.od[index][sub]
        self.node.set_data(index, sub, v.encode_raw(value))

    # --- power and NMT ------------------------------------------------------------------
    def power_on(self):
        self.node.data_store.clear()
        self.state = SOD if self.kind == "drive" else NRTSO
        self.zero = self.angle  # incremental counter: 0 here
        self.cw = 0
        self.v_cmd = 0.0
        self.pending = {}
        self.tpdo_last = {}
        self.sync_count = {}
        self.homing = None  # None, "search", "done", "error"
        self.home_dir = 0.0
        self.operational = False
        self.mode_value = self.mode_display = 0
        self.target = 0
        self.cfg_t, self.cfg_r = [], []
        self.node.nmt.send_command(0x82)  # INITIALISING: boot-up
        self.node.nmt.send_command(0x80)  # PRE-OPERATIONAL (heartbeat from 0x1017)

    def on_nmt(self, cmd):
        if cmd == 0x01:
            self.operational = True
            self.tpdo_last, self.sync_count, self.pending = {}, {}, {}
            self.read_pdo_config()
        elif cmd in (0x02, 0x80):
            self.operational = False
        elif cmd in (0x81, 0x82):
            self.operational = False
            keep = {} if cmd == 0x81 else {i: d for i, d in self.node.data_store.items() if i >= 0x2000}
            self.node.data_store.clear()
            self.node.data_store.update(keep)
            if cmd == 0x81:
                self.state = SOD if self.kind == "drive" else NRTSO
                self.zero = self.angle
                self.mode_value = self.mode_display = 0

            def boot_up():
                self.node.nmt.send_command(0x82)
                self.node.nmt.send_command(0x80)

            # After python-canopen's own NMT handler (it runs after ours) set its state.
            threading.Timer(0.002, boot_up).start()

    # --- CiA 402 ------------------------------------------------------------------------
    def mode(self):
        return self.mode_display if self.kind == "drive" else 0

    def controlword(self, cw):
        prev, self.cw = self.cw, cw
        s = self.state
        if cw & 0x80 and not prev & 0x80:
            if s == FAULT:
                self.state = SOD
                self.put(0x603F, 0, 0)
                self.put(0x1001, 0, 0)
                self.node.emcy.send(0x0000, 0)
            return
        ev, qs, so, eo = cw & 2, cw & 4, cw & 1, cw & 8
        if not ev:
            if s in (RTSO, SO, OE, QSA):
                self.state = SOD
        elif not qs:
            if s == OE:
                self.state = QSA
            elif s in (RTSO, SO):
                self.state = SOD
        elif not so:  # shutdown
            if s in (SOD, SO, OE):
                self.state = RTSO
        elif not eo:  # switch on / disable operation
            if s in (RTSO, OE):
                self.state = SO
        else:  # enable operation
            if s in (SO, QSA):
                self.state = OE
            elif s == RTSO:
                self.state = OE
        if self.state != OE:
            self.homing = self.homing if self.homing in ("done", "error") else None
        if self.mode() == 6 and self.state == OE and cw & 0x10 and not prev & 0x10:
            self.start_homing()

    def start_homing(self):
        method = self.get(0x6098)
        self.homings += 1
        if method in (35, 37):
            self.zero = self.angle
            self.homing = "done"
            return
        if method not in (19, 20):
            self.homing = "error"
            return
        self.homing = "search"
        self.home_from = self.angle
        # Positive home switch: inactive → move positive into it; active → negative out.
        self.home_dir = -1.0 if self.switch() else 1.0

    def switch(self):
        if self.role != "steer":
            return False
        d = math.remainder(self.angle - EDGES[self.wheel], 2 * math.pi)
        return 0.0 <= d < math.pi

    def statusword(self):
        sw = STATE_BITS[self.state] | 0x0200 | 0x8000  # remote; bit 15 manufacturer-specific
        if self.state in (RTSO, SO, OE, QSA):
            sw |= 0x10
        if self.mode() == 6:
            if self.homing in (None, "done", "error"):
                sw |= 0x0400
            if self.homing == "done":
                sw |= 0x1000
            if self.homing == "error":
                sw |= 0x2000
        elif self.state == OE and self.mode() == 9:
            sw |= 0x1000
        return sw

    def fault(self, code, register):
        self.put(0x603F, 0, code)
        self.put(0x1001, 0, register)
        self.put(0x1003, 1, code)
        self.put(0x1003, 0, 1)
        self.node.emcy.send(code, register)
        self.state = FAULT

    # --- motion -------------------------------------------------------------------------
    def units_per_rad(self):
        return INCR * self.gear / (2 * math.pi)

    def step(self, dt):
        if self.kind != "drive":
            return
        target = 0.0
        if self.state == OE and self.mode() == 9 and not self.cw & 0x100:
            target = self.target / self.units_per_rad()
        elif self.state == OE and self.mode() == 6 and self.homing == "search":
            speed = self.get(0x6099, 1) / self.units_per_rad()
            target = self.home_dir * speed
        before = self.angle
        if self.state == OE:
            self.rate += (target - self.rate) * min(1.0, dt / TAU_MOTOR)
        else:  # power stage off: the axis coasts to rest quickly
            self.rate *= max(0.0, 1.0 - dt / 0.05)
        self.angle += self.rate * dt
        if self.homing == "search":
            e = EDGES[self.wheel]
            a = math.remainder(before - e, 2 * math.pi)
            b = a + (self.angle - before)
            if (a < 0.0 <= b) or (b < 0.0 <= a):
                self.zero = before - a  # the edge, unwrapped: position 0 there
                self.homing = "done"
            elif abs(self.angle - self.home_from) > 4 * math.pi:
                self.homing = "error"

    # --- PDOs ---------------------------------------------------------------------------
    def mapping(self, map_index):
        n = self.get(map_index, 0)
        return [(e >> 16, (e >> 8) & 0xFF, e & 0xFF) for e in (self.get(map_index, s) for s in range(1, n + 1))]

    def read_pdo_config(self):
        """The PDOs as the master configured them by SDO, read once when started."""
        self.cfg_t = []
        for k in range(self.tpdos()):
            c = 0x1800 + k
            self.cfg_t.append((self.get(c, 1), self.get(c, 2), self.get(c, 3) * 1e-4, self.get(c, 5) * 1e-3, self.mapping(0x1A00 + k)))
        self.cfg_r = []
        if self.kind == "drive":
            for k in range(4):
                c = 0x1400 + k
                self.cfg_r.append((self.get(c, 1), self.get(c, 2), self.mapping(0x1600 + k)))

    def tpdo_frame(self, k):
        data = b""
        for index, sub, bits in self.cfg_t[k][4]:
            v = self.value(index, sub)
            if v is None:
                data += self.node.get_data(index, sub)[: bits // 8]
            else:
                data += (v & ((1 << bits) - 1)).to_bytes(bits // 8, "little")
        return data

    def send_tpdo(self, k, now):
        data = self.tpdo_frame(k)
        self.net.send_message(self.cfg_t[k][0] & 0x7FF, data)
        self.tpdo_last[k] = (now, data)

    def tpdos(self):
        return 4 if self.kind == "drive" else 2

    def on_sync(self, now):
        if not self.operational:
            return
        for k, values in list(self.pending.items()):
            self.apply_rpdo(k, values)
        self.pending = {}
        for k in range(len(self.cfg_t)):
            cob, ty = self.cfg_t[k][0], self.cfg_t[k][1]
            if cob & 0x80000000 or not 1 <= ty <= 240:
                continue
            c = self.sync_count.get(k, 0) + 1
            if c >= ty:
                c = 0
                self.send_tpdo(k, now)
            self.sync_count[k] = c

    def event_tpdos(self, now):
        if not self.operational:
            return
        for k, (cob, ty, inhibit, timer, _) in enumerate(self.cfg_t):
            if cob & 0x80000000 or ty < 254:
                continue
            data = self.tpdo_frame(k)
            last = self.tpdo_last.get(k)
            if last is None or (data != last[1] and now >= last[0] + inhibit) or (timer and now >= last[0] + timer):
                self.send_tpdo(k, now)

    def on_rpdo(self, can_id, data):
        if not self.operational or self.kind != "drive":
            return
        for k, (cob, ty, m) in enumerate(self.cfg_r):
            if cob & 0x80000000 or cob & 0x7FF != can_id:
                continue
            if len(data) != sum(b // 8 for _, _, b in m):
                self.node.emcy.send(0x8210, 0x11)
                return
            if ty <= 240:
                self.pending[k] = bytes(data)
            else:
                self.apply_rpdo(k, bytes(data))

    def apply_rpdo(self, k, data):
        pos = 0
        for index, sub, bits in self.cfg_r[k][2]:
            chunk = data[pos : pos + bits // 8]
            pos += bits // 8
            if index == 0x6040:
                self.controlword(struct.unpack("<H", chunk)[0])
            elif index == 0x60FF:
                self.target = struct.unpack("<i", chunk)[0]
            else:
                self.node.set_data(index, sub, chunk)

    def on_sdo_write(self, index, subindex, od, data):
        if index == 0x6060:
            # The display follows the mode a few ms later, as on many drives.
            mode = struct.unpack("<b", bytes(data[:1]))[0]
            self.mode_value = mode

            def follow():
                self.mode_display = mode

            threading.Timer(0.008, follow).start()
            if mode != 6:
                self.homing = None


def main():
    # Hand the interpreter lock over often: the SYNC answers (python-can's receive thread)
    # must not wait for the motion loop's turn.
    sys.setswitchinterval(0.0002)
    host, port, channel, seed = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
    rng = random.Random(seed)
    net = canopen.Network()
    net.connect(interface="socketcand", host=host, port=port, channel=channel, tcp_tune=True)
    # One writer at a time on the TCP socket: the SDO server and SYNC answers (notifier
    # thread), the event-driven PDOs (our loop) and the heartbeats (python-can's periodic
    # threads) all send; interleaved writes would corrupt the stream.
    send_lock = threading.Lock()
    raw_send = net.bus.send

    def locked_send(msg, timeout=None):
        with send_lock:
            return raw_send(msg, timeout)

    net.bus.send = locked_send
    eds_dir = tempfile.mkdtemp(prefix="rollbase-interop-eds-")
    devices = {}
    big = threading.Lock()

    def nmt(can_id, data, ts):
        if len(data) != 2:
            return
        with big:
            for n, d in devices.items():
                if data[1] in (0, n):
                    d.on_nmt(data[0])

    # Our NMT handler first: an exception in one of python-canopen's own handlers (they run
    # one after the other for the same frame) must not keep a command from our devices.
    net.subscribe(0, nmt)
    for w in range(4):
        devices[1 + 2 * w] = Device(net, 1 + 2 * w, "drive", "drive", w, eds_dir)
        devices[2 + 2 * w] = Device(net, 2 + 2 * w, "drive", "steer", w, eds_dir, rng.uniform(-3.0, 3.0))
        devices[9 + w] = Device(net, 9 + w, "encoder", "leg", w, eds_dir)
    for d in devices.values():
        d.node.add_write_callback(d.on_sdo_write)

    def sync(can_id, data, ts):
        now = time.monotonic()
        with big:
            for d in devices.values():
                d.on_sync(now)

    net.subscribe(0x80, sync)
    for n, d in devices.items():
        if d.kind == "drive":
            for base in (0x200, 0x300, 0x400, 0x500):
                net.subscribe(base + n, lambda i, data, ts, d=d: _locked(big, d.on_rpdo, i, data))
    stop = threading.Event()

    def loop():
        last = time.monotonic()
        while not stop.is_set():
            time.sleep(0.002)
            now = time.monotonic()
            dt, last = now - last, now
            with big:
                for d in devices.values():
                    d.step(dt)
                    d.event_tpdos(now)

    threading.Thread(target=loop, daemon=True).start()
    print("devices ready", flush=True)
    for line in sys.stdin:
        parts = line.split()
        if not parts:
            continue
        with big:
            if parts[0] == "quit":
                break
            if parts[0] == "emcy":
                d = devices[int(parts[1])]
                code, reg = int(parts[2], 0), int(parts[3], 0)
                if reg == 0:
                    d.node.emcy.send(code, 0)
                else:
                    d.fault(code, reg)
            elif parts[0] == "set":
                # A value set otherwise at the factory: set NODE INDEX SUB VALUE.
                devices[int(parts[1])].put(int(parts[2], 0), int(parts[3], 0), int(parts[4], 0))
            elif parts[0] == "powercycle":
                devices[int(parts[1])].power_on()
            elif parts[0] == "debug":
                out = {
                    str(n): {
                        "op": d.operational,
                        "nmt": d.node.nmt.state,
                        "rpdo": [hex(c[0]) for c in d.cfg_r],
                        "tpdo": [hex(c[0]) for c in d.cfg_t],
                        "cw": d.cw,
                        "mode": d.mode_display,
                    }
                    for n, d in devices.items()
                    if d.kind == "drive"
                }
                print(json.dumps(out), flush=True)
            elif parts[0] == "state":
                out = {
                    str(n): {
                        "angle": d.angle,
                        "homings": d.homings,
                        "state": d.state,
                        "counter": d.get(0x6064) if d.kind == "drive" else 0,
                    }
                    for n, d in devices.items()
                }
                print(json.dumps(out), flush=True)
    stop.set()
    net.disconnect()


def _locked(lock, f, *args):
    with lock:
        f(*args)


if __name__ == "__main__":
    main()
