"""EDS files (CiA 306) for the independent CiA 402 drives and CiA 406 encoders of the
interoperability tests, written from CiA 301 v4.2, CiA 402 (IEC 61800-7-201) and CiA 406:
object indices, data types, access and default values are the standards', not rollbase's.

`write_eds(path, kind, node)` writes one file; python-canopen's `import_od` reads it back
for the `LocalNode`s in cia402_devices.py. COB-IDs are written `$NODEID+0x180` (CiA 306), so
one file serves every node of a kind.

`python3 cia402_eds.py DIR` writes the fixtures rollbase's EDS check is tested with
(driver/tests/eds/): drive.eds, encoder.eds, and broken drives (each one change from
drive.eds): missing-6060.eds (no modes of operation), readonly-6007.eds (abort connection
option code read-only), range-6007.eds (its HighLimit 0, below the plan's 1), unmappable-6041.eds
(statusword not PDO-mappable), and drive.dcf (drive.eds with ParameterValues: quick stop
option 0x605A = 6, quick stop deceleration 0x6085, and a read-only value that is not written).
"""

import sys

# CiA 301 data type codes.
I8, I16, I32, U8, U16, U32, VSTR = 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x09


def _var(index, sub, name, dtype, access, default, pdo=0, low=None, high=None):
    return (index, sub, name, dtype, access, default, pdo, low, high)


NODE = "$NODEID"


def _comm_objects(kind, node):
    """The CiA 301 communication area of a device of `kind` ('drive' or 'encoder')."""
    device_type = 0x00020192 if kind == "drive" else 0x00080196
    name = "independent CiA 402 drive" if kind == "drive" else "independent CiA 406 encoder"
    v = [
        _var(0x1000, None, "Device type", U32, "ro", device_type),
        _var(0x1001, None, "Error register", U8, "ro", 0, 1),
        _var(0x1003, 0, "Number of errors", U8, "rw", 0),
        _var(0x1003, 1, "Standard error field", U32, "ro", 0),
        _var(0x1005, None, "COB-ID SYNC", U32, "rw", 0x80),
        _var(0x1006, None, "Communication cycle period", U32, "rw", 0),
        _var(0x1008, None, "Manufacturer device name", VSTR, "const", name),
        _var(0x1017, None, "Producer heartbeat time", U16, "rw", 0),
        _var(0x1018, 0, "Number of entries", U8, "ro", 4),
        _var(0x1018, 1, "Vendor-ID", U32, "ro", 0),
        _var(0x1018, 2, "Product code", U32, "ro", 0x402 if kind == "drive" else 0x406),
        _var(0x1018, 3, "Revision number", U32, "ro", 1),
        _var(0x1018, 4, "Serial number", U32, "ro", f"{NODE}+0x0"),
        _var(0x2000, None, "Label", VSTR, "rw", "-"),
    ]
    n_tpdo = 4 if kind == "drive" else 2
    for k in range(n_tpdo):
        base = 0x180 + 0x100 * k
        # TPDO1 valid from the factory (and, on the encoder, TPDO2 too: a factory default
        # left on that the master must switch off).
        valid = k == 0 or (kind == "encoder" and k == 1)
        cob = f"{NODE}+0x{(0 if valid else 0x80000000) | 0x40000000 | base:X}"
        v += [
            _var(0x1800 + k, 0, "Highest sub-index", U8, "ro", 5),
            _var(0x1800 + k, 1, "COB-ID", U32, "rw", cob),
            _var(0x1800 + k, 2, "Transmission type", U8, "rw", 1 if kind == "encoder" else 255),
            _var(0x1800 + k, 3, "Inhibit time", U16, "rw", 0),
            _var(0x1800 + k, 5, "Event timer", U16, "rw", 0),
            _var(0x1A00 + k, 0, "Number of mapped objects", U8, "rw", 1 if valid else 0),
        ]
        first = 0x60410010 if kind == "drive" else 0x60040020
        for s in range(1, 9):
            v.append(_var(0x1A00 + k, s, f"Mapped object {s}", U32, "rw", first if (valid and s == 1) else 0))
    if kind == "drive":
        v += [
            _var(0x1016, 0, "Number of entries", U8, "ro", 1),
            _var(0x1016, 1, "Consumer heartbeat time", U32, "rw", 0),
        ]
        for k in range(4):
            base = 0x200 + 0x100 * k
            cob = f"{NODE}+0x{(0 if k == 0 else 0x80000000) | base:X}"
            v += [
                _var(0x1400 + k, 0, "Highest sub-index", U8, "ro", 5),
                _var(0x1400 + k, 1, "COB-ID", U32, "rw", cob),
                _var(0x1400 + k, 2, "Transmission type", U8, "rw", 255),
                _var(0x1400 + k, 5, "Event timer", U16, "rw", 0),
                _var(0x1600 + k, 0, "Number of mapped objects", U8, "rw", 1 if k == 0 else 0),
            ]
            for s in range(1, 9):
                v.append(_var(0x1600 + k, s, f"Mapped object {s}", U32, "rw", 0x60400010 if (k == 0 and s == 1) else 0))
    return v


def _profile_objects(kind):
    if kind == "encoder":
        return [
            _var(0x6004, None, "Position value", U32, "ro", 0, 1),
            _var(0x6005, 0, "Highest sub-index", U8, "ro", 2),
            _var(0x6005, 1, "Position measuring step", U32, "ro", 1000),
            _var(0x6005, 2, "Speed measuring step", U32, "ro", 10),
            _var(0x6030, 0, "Highest sub-index", U8, "ro", 1),
            _var(0x6030, 1, "Speed value channel 1", I16, "ro", 0, 1),
        ]
    return [
        # CiA 402: 0 no action, 1 fault, 2 disable voltage, 3 quick stop; below 0 the
        # manufacturer's.
        _var(0x6007, None, "Abort connection option code", I16, "rw", 1, 0, -32768, 3),
        _var(0x603F, None, "Error code", U16, "ro", 0, 1),
        _var(0x6040, None, "Controlword", U16, "rw", 0, 1),
        _var(0x6041, None, "Statusword", U16, "ro", 0, 1),
        # CiA 402: 0 disable drive function; 1..4 slow down (ramp, quick stop ramp, current
        # limit, voltage limit) then switch on disabled; 5..8 the same, staying in quick stop
        # active.
        _var(0x605A, None, "Quick stop option code", I16, "rw", 2, 0, -32768, 8),
        _var(0x6060, None, "Modes of operation", I8, "rw", 0, 1),
        _var(0x6061, None, "Modes of operation display", I8, "ro", 0, 1),
        _var(0x6064, None, "Position actual value", I32, "ro", 0, 1),
        _var(0x606C, None, "Velocity actual value", I32, "ro", 0, 1),
        _var(0x607C, None, "Home offset", I32, "rw", 0),
        # Bit 7 position polarity, bit 6 velocity polarity.
        _var(0x607E, None, "Polarity", U8, "rw", 0),
        _var(0x6085, None, "Quick stop deceleration", U32, "rw", 0x7FFFFFFF),
        _var(0x608F, 0, "Highest sub-index", U8, "ro", 2),
        _var(0x608F, 1, "Encoder increments", U32, "rw", 16384),
        _var(0x608F, 2, "Motor revolutions", U32, "rw", 1),
        _var(0x6098, None, "Homing method", I8, "rw", 0),
        _var(0x6099, 0, "Highest sub-index", U8, "ro", 2),
        _var(0x6099, 1, "Speed during search for switch", U32, "rw", 0),
        _var(0x6099, 2, "Speed during search for zero", U32, "rw", 0),
        _var(0x609A, None, "Homing acceleration", U32, "rw", 0),
        # Prefix (bits 24-31), unit (16-23), time unit (8-15): 0x00B50300 increments per
        # second (CiA 402 factor group; the codes as in CiA 303-2).
        _var(0x60A9, None, "SI unit velocity", U32, "rw", 0x00B50300),
        _var(0x60C2, 0, "Highest sub-index", U8, "ro", 2),
        _var(0x60C2, 1, "Interpolation time period value", U8, "rw", 1),
        _var(0x60C2, 2, "Interpolation time index", I8, "rw", -3),
        _var(0x60FD, None, "Digital inputs", U32, "ro", 0, 1),
        _var(0x60FF, None, "Target velocity", I32, "rw", 0, 1),
    ]


def _fmt_default(dtype, default):
    if dtype == VSTR or isinstance(default, str):
        return str(default)
    if isinstance(default, int) and default < 0:
        return str(default)
    return f"0x{default:X}" if isinstance(default, int) and default > 9 else str(default)


def _broken(objs, variant):
    """One change to a drive's objects (see the module docs); `params`: DCF values."""
    out = []
    for o in objs:
        index, sub, name, dt, acc, dflt, pdo, low, high = o
        if variant == "missing-6060" and index == 0x6060:
            continue
        if variant == "readonly-6007" and index == 0x6007:
            acc = "ro"
        if variant == "range-6007" and index == 0x6007:
            high = 0
        if variant == "unmappable-6041" and index == 0x6041:
            pdo = 0
        out.append((index, sub, name, dt, acc, dflt, pdo, low, high))
    return out


# ParameterValues of the fixture DCF (index, sub) -> value.
DCF_VALUES = {(0x605A, None): 6, (0x6085, None): 200000, (0x6041, None): 0x1234}


def eds_text(kind, node, variant=None, params=None):
    """The EDS of a device of `kind` at `node` (its PDO COB-IDs: $NODEID+…); `variant` one
    of the broken drives; `params` the ParameterValues of a DCF."""
    objs = _comm_objects(kind, node) + _profile_objects(kind)
    if variant:
        objs = _broken(objs, variant)
    params = params or {}
    by_index = {}
    for o in objs:
        by_index.setdefault(o[0], []).append(o)
    mandatory = [0x1000, 0x1001, 0x1018]
    manufacturer = [i for i in by_index if 0x2000 <= i < 0x6000]
    optional = [i for i in sorted(by_index) if i not in mandatory and i not in manufacturer]
    out = [
        "[FileInfo]",
        f"FileName=rollbase-interop-{kind}.eds",
        "FileVersion=1",
        "Description=Independent device for rollbase's interoperability tests",
        "CreatedBy=rollbase interop (written from CiA 301/402/406)",
        "EDSVersion=4.0",
        "",
        "[DeviceInfo]",
        "VendorName=rollbase interop",
        f"ProductName=independent {kind}",
        "BaudRate_1000=1",
        "SimpleBootUpSlave=1",
        "Granularity=8",
        f"NrOfRXPDO={4 if kind == 'drive' else 0}",
        f"NrOfTXPDO={4 if kind == 'drive' else 2}",
        "",
    ]
    for title, idxs in (("MandatoryObjects", mandatory), ("OptionalObjects", optional), ("ManufacturerObjects", manufacturer)):
        out.append(f"[{title}]")
        out.append(f"SupportedObjects={len(idxs)}")
        for k, i in enumerate(idxs, 1):
            out.append(f"{k}=0x{i:04X}")
        out.append("")
    def body(index, sub, name, dt, acc, dflt, pdo, low, high):
        lines = [f"ParameterName={name}", "ObjectType=0x7", f"DataType=0x{dt:04X}", f"AccessType={acc}"]
        if low is not None:
            lines.append(f"LowLimit={low}")
        if high is not None:
            lines.append(f"HighLimit={high}")
        lines += [f"DefaultValue={_fmt_default(dt, dflt)}", f"PDOMapping={pdo}"]
        if (index, sub) in params:
            lines.append(f"ParameterValue={_fmt_default(dt, params[(index, sub)])}")
        return lines + [""]

    for i in sorted(by_index):
        entries = by_index[i]
        if len(entries) == 1 and entries[0][1] is None:
            out += [f"[{i:04X}]"] + body(*entries[0])
            continue
        subs = sorted(entries, key=lambda e: e[1])
        out += [f"[{i:04X}]", f"ParameterName=Object 0x{i:04X}", "ObjectType=0x9", f"SubNumber={len(subs)}", ""]
        for e in subs:
            out += [f"[{i:04X}sub{e[1]}]"] + body(*e)
    return "\n".join(out) + "\n"


def write_eds(path, kind, node, variant=None, params=None):
    with open(path, "w") as f:
        f.write(eds_text(kind, node, variant, params))
    return path


FIXTURES = {
    "drive.eds": ("drive", None, None),
    "encoder.eds": ("encoder", None, None),
    "missing-6060.eds": ("drive", "missing-6060", None),
    "readonly-6007.eds": ("drive", "readonly-6007", None),
    "range-6007.eds": ("drive", "range-6007", None),
    "unmappable-6041.eds": ("drive", "unmappable-6041", None),
    "drive.dcf": ("drive", None, DCF_VALUES),
}


def write_fixtures(directory):
    """Every fixture of the module docs into `directory`; returns their paths."""
    return [write_eds(f"{directory}/{name}", kind, 1, variant, params) for name, (kind, variant, params) in FIXTURES.items()]


if __name__ == "__main__":
    for p in write_fixtures(sys.argv[1]):
        print(p)
