//! `docs/cia402.md`, generated from the profile's tables: the frames, the PDO mappings, the
//! boot plan every device receives, the state machine the master drives, the supervision,
//! and the bus load of the default platform.

use super::busload;
use super::config::{Cia402Config, Role, SdoOp};
use super::emcy;
use super::od;
use super::pdo::{self, PdoLayout};
use std::fmt::Write as _;

/// The name of an object (for the documentation and messages).
pub fn object_name(index: u16, sub: u8) -> String {
    let comm = |base: u16, what: &str| -> Option<String> {
        if (base..base + 4).contains(&index) {
            let n = index - base + 1;
            let field = match sub {
                0 => "highest sub-index",
                1 => "COB-ID",
                2 => "transmission type",
                3 => "inhibit time",
                5 => "event timer",
                _ => "entry",
            };
            Some(format!("{what}{n} {field}"))
        } else {
            None
        }
    };
    let map = |base: u16, what: &str| -> Option<String> {
        if (base..base + 4).contains(&index) {
            let n = index - base + 1;
            Some(if sub == 0 {
                format!("{what}{n} mapping: number of entries")
            } else {
                format!("{what}{n} mapping entry {sub}")
            })
        } else {
            None
        }
    };
    if let Some(s) = comm(od::RPDO_COMM, "RPDO")
        .or_else(|| comm(od::TPDO_COMM, "TPDO"))
        .or_else(|| map(od::RPDO_MAP, "RPDO"))
        .or_else(|| map(od::TPDO_MAP, "TPDO"))
    {
        return s;
    }
    match (index, sub) {
        (od::DEVICE_TYPE, _) => "device type",
        (od::ERROR_REGISTER, _) => "error register",
        (od::COMM_CYCLE_PERIOD, _) => "communication cycle period (µs)",
        (od::CONSUMER_HEARTBEAT, _) => "consumer heartbeat time (node-ID in bits 16–23, ms)",
        (od::PRODUCER_HEARTBEAT, _) => "producer heartbeat time (ms)",
        (od::IDENTITY, _) => "identity",
        (od::ABORT_CONNECTION_OPTION, _) => "abort connection option code",
        (od::CONTROLWORD, _) => "controlword",
        (od::STATUSWORD, _) => "statusword",
        (od::MODES_OF_OPERATION, _) => "modes of operation",
        (od::MODES_OF_OPERATION_DISPLAY, _) => "modes of operation display",
        (od::POSITION_ACTUAL, _) => "position actual value",
        (od::VELOCITY_ACTUAL, _) => "velocity actual value",
        (od::INTERPOLATION_TIME_PERIOD, 1) => "interpolation time period value",
        (od::INTERPOLATION_TIME_PERIOD, 2) => "interpolation time index (10^index s)",
        (od::TARGET_VELOCITY, _) => "target velocity",
        (od::PRE_DEFINED_ERROR_FIELD, _) => "pre-defined error field",
        (od::DEVICE_NAME, _) => "manufacturer device name",
        (od::ERROR_CODE, _) => "error code",
        (od::QUICK_STOP_OPTION, _) => "quick stop option code",
        (od::QUICK_STOP_DECELERATION, _) => "quick stop deceleration",
        (od::FAULT_REACTION_OPTION, _) => "fault reaction option code",
        (od::HOME_OFFSET, _) => "home offset",
        (od::POLARITY, _) => "polarity",
        (od::POSITION_ENCODER_RESOLUTION, 1) => "position encoder resolution: encoder increments",
        (od::POSITION_ENCODER_RESOLUTION, 2) => "position encoder resolution: motor revolutions",
        (od::GEAR_RATIO, 1) => "gear ratio: motor revolutions",
        (od::GEAR_RATIO, 2) => "gear ratio: shaft revolutions",
        (od::HOMING_METHOD, _) => "homing method",
        (od::HOMING_SPEEDS, 1) => "homing speed during search for switch",
        (od::HOMING_SPEEDS, 2) => "homing speed during search for zero",
        (od::HOMING_ACCELERATION, _) => "homing acceleration",
        (od::SI_UNIT_VELOCITY, _) => "SI unit velocity",
        (od::DIGITAL_INPUTS, _) => "digital inputs",
        (od::POSITION_VALUE, _) => "position value",
        (od::MEASURING_STEP, 1) => "position measuring step (nm)",
        (od::MEASURING_STEP, 2) => "speed measuring step",
        (od::SPEED_VALUE, _) => "speed value",
        _ => "object",
    }
    .to_string()
}

fn layout_row(s: &mut String, what: &str, l: &PdoLayout, transmission: &str) {
    let cob = match l.dir {
        pdo::Direction::Rx => format!("0x{:03X} + node", l.cob_id(0)),
        pdo::Direction::Tx => format!("0x{:03X} + node", l.cob_id(0)),
    };
    let entries: Vec<String> = l
        .entries
        .iter()
        .map(|e| {
            format!(
                "0x{:04X}:{:02X} {} ({} bits)",
                e.index,
                e.sub,
                object_name(e.index, e.sub),
                e.bits
            )
        })
        .collect();
    let _ = writeln!(
        s,
        "| {what} | {cob} | {} | {} | {transmission} |",
        entries.join(", "),
        l.len_bytes()
    );
}

fn bytes(n: usize) -> String {
    if n == 1 {
        "1 byte".into()
    } else {
        format!("{n} bytes")
    }
}

fn plan_table(s: &mut String, cfg: &Cia402Config, role: Role, period_us: u32) {
    plan_table_from(s, cfg, role, period_us, 0);
}

fn plan_table_from(s: &mut String, cfg: &Cia402Config, role: Role, period_us: u32, from: usize) {
    s.push_str("| # | object | name | operation |\n|---|---|---|---|\n");
    for (i, op) in cfg.plan(role, period_us).iter().enumerate().skip(from) {
        let (index, sub) = op.object();
        let what = match op {
            SdoOp::Write { data, .. } => {
                let cob_write = sub == od::PDO_COB_ID
                    && ((od::RPDO_COMM..od::RPDO_COMM + 4).contains(&index)
                        || (od::TPDO_COMM..od::TPDO_COMM + 4).contains(&index));
                if cob_write {
                    format!(
                        "write 0x{:08X} + node ({})",
                        data.as_u32(),
                        bytes(data.len())
                    )
                } else {
                    format!("write 0x{:X} ({})", data.as_u32(), bytes(data.len()))
                }
            }
            SdoOp::Verify {
                mask,
                expected,
                what,
                poll_ms,
                ..
            } if *poll_ms > 0 => format!(
                "read every cycle until value & 0x{mask:X} = 0x{expected:X}, at most {poll_ms} ms: {what}"
            ),
            SdoOp::Verify {
                mask,
                expected,
                what,
                ..
            } => format!("read, require value & 0x{mask:X} = 0x{expected:X}: {what}"),
        };
        let what = if op.optional() {
            format!("{what} (optional: skipped if the object does not exist)")
        } else {
            what
        };
        let _ = writeln!(
            s,
            "| {} | 0x{index:04X}:{sub:02X} | {} | {what} |",
            i + 1,
            object_name(index, sub)
        );
    }
    s.push('\n');
}

/// `docs/cia402.md` for the default configuration of a 4-wheel platform at 250 Hz.
pub fn markdown() -> String {
    let cfg = Cia402Config::for_wheels(4);
    let period_us = 4000;
    let mut s = String::new();
    s.push_str("# rollbase CiA 402 profile (CANopen drives and encoders)\n\n");
    s.push_str(
        "<!-- Generated from driver/src/canopen/ by rollbase_driver::canopen::doc::markdown(). \
         Do not edit: regenerate with `cargo run -- cia402-doc > docs/cia402.md` or \
         `UPDATE_DOCS=1 cargo test -p rollbase-driver --test cia402_doc`. -->\n\n",
    );
    s.push_str(
        "The second wire profile of rollbase, selected in the platform file with \
         `protocol = \"cia402\"` and configured in its `[cia402]` table (`rollbase config default \
         --profile cia402` prints every field). Each wheel is three CANopen devices: a rolling \
         drive and a steering drive speaking CiA 402 in cyclic synchronous velocity mode, and \
         the leg's absolute linear encoder speaking CiA 406. The same controller, supervisor and \
         recording run on it; only the link changes (`control/src/runtime/link.rs`). The facts used \
         (COB-IDs, SDO and NMT command specifiers, statusword and controlword bits, state \
         transitions, device-type encoding) are those of CiA 301 v4.2, CiA 402 \
         (IEC 61800-7-201) and CiA 406 v3.1.\n\n",
    );

    s.push_str("## Devices (default assignment)\n\n");
    s.push_str("| wheel | rolling drive | steering drive | leg encoder |\n|---|---|---|---|\n");
    for (i, w) in cfg.wheels.iter().enumerate() {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} |",
            i + 1,
            w.drive_node,
            w.steer_node,
            w.leg_node
        );
    }
    let _ = writeln!(
        s,
        "\nThe master produces its heartbeat as node {}. Node-IDs are free in 1..=127 \
         (`[[cia402.wheels]]`), each used once.\n",
        cfg.master_node
    );

    s.push_str("## Frames\n\n");
    s.push_str(
        "| frame | COB-ID | direction | DLC | when |\n|---|---|---|---|---|\n\
         | NMT command | 0x000 | master → device | 2 | boot (reset communication, start), re-arm |\n\
         | SYNC | 0x080 | master → all | 0 | every cycle, first frame of the cycle |\n\
         | EMCY | 0x080 + node | device → all | 8 | on an error and on its reset (code 0) |\n\
         | TPDO1 | 0x180 + node | device → master | 8 (drive), 6 (encoder) | every SYNC |\n\
         | RPDO1 | 0x200 + node | master → drive | 6 | every cycle, after the control step |\n\
         | TPDO2 | 0x280 + node | drive → master | 2 | statusword change (inhibit time), event timer |\n\
         | SDO request | 0x600 + node | master → device | 8 | boot (configuration), after homing, after a drive fault (0x603F, 0x1003:01) |\n\
         | SDO response | 0x580 + node | device → master | 8 | answers |\n\
         | boot-up / heartbeat | 0x700 + node | device → all | 1 | boot-up once; heartbeat every `heartbeat_ms` |\n\
         | master heartbeat | 0x700 + master node | master → drives | 1 | every `master_heartbeat_ms` |\n\n",
    );
    s.push_str(
        "The master's SDO transfers are expedited (every object it reads or writes is at most 4 \
         bytes); a device answering one of them with a segmented transfer fails the boot with a \
         message saying so. `rollbase sdo --bus BUS --node N read|write INDEX:SUB [VALUE]` reads \
         and writes any object, expedited or segmented (strings such as the device name 0x1008), \
         for bring-up and diagnosis; it refuses to run while a master's SYNC is on the bus.\n\n",
    );

    s.push_str("## PDO mappings\n\n");
    s.push_str("| PDO | COB-ID | mapped objects | bytes | transmission |\n|---|---|---|---|---|\n");
    let rpdo_tx = format!(
        "{} (synchronous: applied at the next SYNC)",
        cfg.rpdo_transmission
    );
    layout_row(&mut s, "drive RPDO1", &pdo::DRIVE_RPDO1, &rpdo_tx);
    layout_row(&mut s, "drive TPDO1", &pdo::DRIVE_TPDO1, "1 (every SYNC)");
    layout_row(
        &mut s,
        "drive TPDO2",
        &pdo::DRIVE_TPDO2,
        "255 (on change, inhibit time; event timer)",
    );
    layout_row(
        &mut s,
        "encoder TPDO1",
        &pdo::ENCODER_TPDO1,
        "1 (every SYNC)",
    );
    s.push_str(
        "\nThe statusword has its own event-driven TPDO: it changes a handful of times per run, \
         and keeping it out of the cyclic TPDO keeps that at 8 bytes. `status_extra` maps more \
         objects into it after the statusword (mapping entries such as 0x603F0010 error code, \
         0x60FD0020 digital inputs, 0x60770010 torque; 8 bytes in all); 0x60FD is added by \
         itself when a steering drive is homed on a digital input. Every other PDO of a device \
         (drives: RPDO2–4, TPDO3–4; encoders: TPDO2–4) is disabled at boot, so that a factory \
         default left on does not load the bus.\n\n",
    );

    s.push_str("## Boot\n\n");
    s.push_str(
        r#"For every device, in parallel: NMT reset communication → wait for its boot-up (at most `boot_timeout_ms`) → the configuration below, one SDO request in flight per device (at most two per cycle), each answered within `sdo_timeout_ms` or repeated `sdo_retries` times → NMT start → (steering drives) homing → every steering axis to its rest angle. The controller arms only then. An abort, a timeout or a value read back that does not match stops the boot; the run ends in Fault with a message naming the node, its role, the object and the abort code. Steps marked optional are skipped when the device answers "object does not exist" (0x06020000) or "sub-index does not exist" (0x06090011), and listed per device (`Device::skipped`). A mode display (0x6061) is read again every cycle until it shows the mode written, for at most `mode_switch_timeout_ms`. The quick stop option 0x605A and deceleration 0x6085 come from `[cia402.quick_stop]` (optional steps). Then, in this order, after the plan's own configuration and before the unit checks and the mode of operation: a DCF's values (`[cia402.eds]`, see below), then the extra writes of `[[cia402.sdo]]` (current limits, fault reaction 0x605E, polarity 0x607E, brake and vendor objects) in the file's order: the platform file has the last word. The unit checks read what the drive ended up with. The PDO COB-IDs below are written with the device's node-ID added.

### Device description files (EDS/DCF, CiA 306)

`[cia402.eds]` names a file per role (`drive`, `steer`, `leg`) and per device (`[[cia402.eds.devices]] node = 4 file = "steer4.dcf"`, before its role's), relative to the platform file. When the platform file is loaded (`rollbase config check`, `drive`, every command that reads it), each file is parsed (INI: `[DeviceInfo]`, the object lists, one section per object and sub-index with `ObjectType`, `DataType`, `AccessType`, `LowLimit`, `HighLimit`, `DefaultValue`, `PDOMapping`, a DCF's `ParameterValue`; `$NODEID` resolved per device) and every step of the device's boot plan is checked against it before any frame is sent: the object exists (optional steps may be missing), a written object is writable and the value has the data type's size and lies within the limits, a read object is readable, a mapped object is PDO-mappable with its data type's length, and the mapping fits the mapping object's entries and 64 bits. A value the plan reads back (encoder resolution, measuring step, units) and the DCF configures otherwise is refused ahead. Each error names the node, role and wheel, the object as 0xIIII:SS, the file, and what to change. A DCF's `ParameterValue`s are written at boot (the order above), in index order, except: read-only objects, objects the plan writes as mandatory steps (PDOs, heartbeat, mode …: the plan's value is the one the master needs; its optional defaults such as 0x605A/0x6085 a DCF does replace), PDO parameters 0x1400–0x1BFF, store/restore 0x1010/0x1011, and values that are not 1–4 bytes; `rollbase config check` lists what it checked and what it did not write.

"#,
    );
    let _ = writeln!(
        s,
        "### Rolling drives, {} steps\n",
        cfg.plan(Role::Drive, period_us).len()
    );
    plan_table(&mut s, &cfg, Role::Drive, period_us);
    let _ = writeln!(
        s,
        "### Steering drives (homed by the drive, the default), {} steps\n\n\
         The same as a rolling drive up to the unit checks; then the homing objects and mode \
         6 instead of 9:\n",
        cfg.plan(Role::Steer, period_us).len()
    );
    let drive_len = cfg.plan(Role::Drive, period_us).len() - 2;
    plan_table_from(&mut s, &cfg, Role::Steer, period_us, drive_len);
    let _ = writeln!(
        s,
        "### Leg encoders, {} steps\n",
        cfg.plan(Role::Leg, period_us).len()
    );
    plan_table(&mut s, &cfg, Role::Leg, period_us);

    s.push_str("## The drive state machine\n\n");
    s.push_str(
        "Every cycle each drive gets the controlword that moves it one step toward the state \
         the supervisor wants, given the state its last statusword showed:\n\n\
         | drive state | enable | controlword |\n|---|---|---|\n\
         | switch on disabled | yes / no | 0x0006 shutdown |\n\
         | ready to switch on | yes | 0x0007 switch on |\n\
         | switched on, operation enabled | yes | 0x000F enable operation (0x010F with halt when braking) |\n\
         | any but fault | no | 0x0006 shutdown (drive function off, at rest) |\n\
         | fault | re-arm | 0x0080 fault reset (rising edge; 0x0000 in between) |\n\
         | fault | otherwise | 0x0000 disable voltage |\n\
         | operation enabled, quick stop active | quick stop commanded (`Master::quick_stop`, until re-armed) | 0x0002 quick stop |\n\
         | quick stop active, not ready, fault reaction active, unknown | | 0x0000 disable voltage |\n\n\
         The target velocity is zero until the drive has reported operation enabled. A target \
         the velocity object cannot carry is sent as zero with halt, and the supervisor's \
         limit check stops the platform. At the end of a run the drives are told to shut down \
         for the last two cycles (a synchronous RPDO acts at the next SYNC), so they end in \
         ready to switch on; the very last cycle then sends NMT reset communication to every \
         device, which returns their heartbeat consumer and RPDO deadline to off: a controller \
         that exits cleanly leaves no communication-loss fault behind. One that dies leaves \
         them monitoring, and they fault within the timeouts below (the fail-safe path).\n\n",
    );

    s.push_str("## Supervision\n\n");
    let _ = writeln!(
        s,
        "| event | who detects | reaction |\n|---|---|---|\n\
         | master heartbeat missing for `device_heartbeat_timeout_ms` ({} ms) | drive | EMCY 0x{:04X}; in operation enabled the 0x6007 reaction (`comm_loss_reaction` = {}: fault) |\n\
         | no RPDO1 for `rpdo_timeout_ms` ({} ms) | drive | EMCY 0x{:04X}; in operation enabled the 0x6007 reaction |\n\
         | device heartbeat missing for `master_heartbeat_timeout_ms` ({} ms) | master | device fault, controlled stop |\n\
         | EMCY, error register 0, or 0x8120 / 0x8140, or in `informational_emcy` | master | logged and counted (informational), kept in the device's EMCY history; not a fault |\n\
         | any other EMCY | master | device fault naming the code, 0x603F read back into it, controlled stop |\n\
         | statusword shows fault | master | device fault (0x603F and 0x1003:01 read back into it), controlled stop |\n\
         | a steering drive's boot-up (rebooted, power cycled) | master | device fault; the re-arm boots it and homes it again (its counter restarted at 0) |\n\
         | the controller's CAN interface bus-off (error frame `CAN_ERR_BUSOFF`) | core (`CycleCore::report_bus_event`), master (`Master::bus_off`) | fault `bus-off` naming the bus and what to check, quick stop; every device of that bus lost, fault latched; the re-arm reopens the socket and boots them all again (see Bus-off below) |\n\
         | error warning / error passive / restarted (error frames, `CAN_ERR_CRTL`, `CAN_ERR_RESTARTED`) | core | counted per bus (state port diagnostics `can`, run summary `can_bus`, ROS 2 `CAN bus` entry), logged once per change (at most one line a second); not a fault |\n\
         | stale feedback (last row) or a bus error: the host cannot close its ramp on what the drives do | core (`Master::quick_stop`) | every enabled drive gets the Quick Stop command (controlword 0x0002) until re-armed, and stops on its own quick-stop ramp (0x605A option, 0x6085 deceleration from `[cia402.quick_stop]`; option 2 then switches on disabled); no drive is enabled again before the re-arm |\n\
         | boot-up or heartbeat state other than operational while running | master | device fault (rebooted / left operational), controlled stop |\n\
         | drive not in operation enabled `enable_timeout_ms` ({} ms) after being asked | master | device fault, controlled stop |\n\
         | no TPDO1 from a device for more than the supervisor's `stale_cycles` (3 cycles, as for the native modules; any device of a wheel) | supervisor | stale feedback naming the node |",
        cfg.device_heartbeat_timeout_ms,
        emcy::codes::HEARTBEAT,
        cfg.comm_loss_reaction,
        cfg.rpdo_timeout_ms,
        emcy::codes::RPDO_TIMEOUT,
        cfg.master_heartbeat_timeout_ms,
        cfg.enable_timeout_ms,
    );
    s.push_str(
        "\nDevice faults are latched until the operator re-arms; re-arming clears them, sends \
         the fault-reset edge to drives in fault and boots again every device that is not \
         running. A drive found in fault when its master boots (the previous controller \
         died and the drive reacted to the loss) is sent the fault reset once every device \
         runs; only a fault still shown `enable_timeout_ms` later is reported. The fault \
         reset is the master's own: it is sent whenever a drive's statusword shows Fault inside \
         that grace period (after the arm, or once every device runs after a boot), however \
         late the statusword comes (the event timer allows it `status_event_timer_ms` late), at \
         most 8 times.\n\n",
    );

    s.push_str("## Bus-off\n\n");
    s.push_str(
        "A CAN controller whose transmit error counter passes 255 goes bus-off (ISO 11898-1): \
         it neither sends nor receives until restarted. The usual causes are wiring and \
         connectors, a missing or extra termination (120 ohm at both ends only), a node at \
         another bit rate, or a node that babbles. rollbase reads the controller's error \
         frames (Linux `include/uapi/linux/can/error.h`; SocketCAN delivers them with the \
         error mask rollbase sets, socketcand as `< error CLASS TIME >` with the class only) \
         as typed events: warning and error passive are counted and logged, bus-off faults \
         the platform at once (`bus-off: the controller's CAN interface on bus B went \
         bus-off ...`). The drives, no longer hearing the master's heartbeat and RPDOs, stop \
         on their communication-loss reaction within `rpdo_timeout_ms` / \
         `device_heartbeat_timeout_ms`; the master takes every device of that bus as lost \
         (`Master::bus_off`).\n\n\
         Restarting the controller is the kernel's job and needs CAP_NET_ADMIN, which the \
         driver does not ask for: configure the interface to restart itself, \
         `sudo ip link set can0 type can bitrate 1000000 restart-ms 100` (or restart it by \
         hand: `sudo ip link set can0 type can restart`). Without `restart-ms` the interface \
         stays bus-off and every re-arm faults again. The restart is reported \
         (`restarted`) and counted, but nothing moves: the fault stays latched until the \
         operator re-arms (from any command source: `{\"rearm\": true}`, the keyboard, the \
         ROS 2 service). The re-arm opens a fresh socket on the interface, then boots every \
         device of the bus again (NMT reset communication, the whole boot plan); steering \
         drives keep their homing (a bus-off does not power-cycle a drive; one that did \
         reboot announces it with its boot-up and is homed again). Native wheel modules have \
         no boot handshake: their setpoint watchdogs tripped, the re-arm's fault reset \
         clears them and the link resumes.\n\n",
    );

    s.push_str("## Homing\n\n");
    s.push_str(
        "An incremental steering encoder reads 0 at power-on wherever the wheel points: until \
         the steering drive is homed its angle means nothing. Every steering drive that booted \
         (power-on, reboot, a new master) is homed when the operator first arms, each wheel as \
         soon as its two drives run; the rolling drive of the wheel is enabled and holds (with \
         `coupling` ≠ 0 it turns −coupling × the steering rate, so a steer→drive gear does not \
         roll the wheel). Then every axis turns to its `rest_angle_rad` on a braking-distance \
         profile at 80 % of `limits.steer_rate` and `limits.steer_accel`, each command through \
         the output guard, and only then does the platform arm. Per wheel: \
         `[cia402.homing]`, or `[cia402.wheels.homing]` for one wheel.\n\n\
         | `kind` | what happens | the home position |\n|---|---|---|\n\
         | `drive` (default) | the drive homes in CiA 402 homing mode (6) with `method` (0x6098), `switch_speed_rad_s` / `index_speed_rad_s` (0x6099:01/02), `accel_rad_s2` (0x609A), 0x607C = 0; controlword bit 4 starts it, statusword bits 12 + 10 end it, bit 13 fails it; then shutdown, mode 9 by SDO (polled) | what the method finds: 3/4 home switch then index pulse, 5/6 likewise with a negative switch, 19–22 the switch edge, 33/34 the index pulse, 35/37 the current position |\n\
         | `digital_input` | the host turns the axis at `switch_speed_rad_s` (signed, ramped at `accel_rad_s2`) in cyclic synchronous velocity until bit `input_bit` of 0x60FD rises (an axis that starts with it set first turns the other way until it clears), takes the position there, ramps down; more than 1.25 turns without it fails | the input's rising edge |\n\
         | `absolute` | no motion: the first angle read must lie within a turn of the encoder's zero | the encoder's zero |\n\
         | `none` | nothing (only for drives that keep their position across power cycles) | — |\n\n\
         The steering angle is the position from the home position plus `steer_offset_rad`: \
         the angle of the home position, measured once at commissioning. A homing that is not \
         done within `timeout_ms`, a homing error, an input never seen, a drive that faults while \
         homing or an axis that does not reach its rest angle within 15 s refuses the arm, \
         naming the wheel, the node and what to check.\n\n\
         A wheel with a `steer_range` (cable stops) must have its `rest_angle_rad` inside the \
         range (`rollbase config check` refuses it otherwise), and its turn to the rest angle \
         stays inside: it turns by the plain difference from the angle it was homed at, the \
         long way round where the short one would cross a stop \
         (`tests/tests/e2e_homing.rs`: homed at −150°, rest at +160°, ±170° stops: +310°). \
         The search before it cannot be bounded by the host: until the axis is homed nobody \
         knows where in its range it stands. Put the home switch where the search reaches it \
         before any stop (at the end of the range the search runs toward), or use an \
         absolute steering encoder.\n\n",
    );

    s.push_str("## Bring-up checklist (first power-on of real drives)\n\n");
    s.push_str(
        r#"1. **Wheels off the ground.** Lift the base so no wheel touches the floor; keep the emergency stop in reach. Nothing moves before you arm, but homing and the turn to the rest angles move every steering axis.
2. **Node-IDs and bit rate**: set them with the vendor's tool; write them into `[[cia402.wheels]]`. `rollbase sdo --bus can0 --node N read 0x1000:00` must answer 0x…0192 (drive) or 0x…0196 (encoder); `read 0x1008:00 --type str` names the device.
3. **Units**: `increments_per_rev` (after quadrature) and `gear_ratio` per drive kind; `velocity_unit` as the drive's 0x60FF/0x606C are scaled. Where the drive has them, the boot reads and checks 0x608F:01/02 (encoder increments per one motor revolution), a 1:1 0x6091 (the platform file converts; the drive must not scale as well) and the SI unit velocity 0x60A9 (CiA 402 factor group, bytes prefix · unit · time unit · reserved, codes of CiA 303-2: 0x00B50300 inc/s, 0x00B44700 rev/min, 0xFDB44700 0.001 rev/min as in Nanotec's and Synapticon's manuals); a mismatch refuses the boot naming the object, the value read and what the file expects. Turn each wheel by hand one revolution and check `rollbase monitor` shows 2π.
4. **Polarity**: a motor mounted mirrored (its positive direction turns the joint the negative way) gets `drive_polarity` / `steer_polarity` = -1 on its `[[wheels]]` entry (host side, per wheel, both profiles), a negative `gear_ratio` (host side, for every drive of that kind), or 0x607E = 0xC0 (position and velocity inverted) as an extra SDO write `[[cia402.sdo]] node = 4 index = 0x607E value = 0xC0 size = 1` (drive side, per drive, and the drive's homing then searches in the joint's directions); only one of them. With the wheels lifted, command a small positive steering rate and wheel speed and check the wheels turn the way the platform's axes say: the host cannot see a wrong sign from the drive's own feedback (it is consistent with its own command).
5. **Homing**: choose `kind` and `method` from the drive manual's 0x6098 table and the machine (switch, index, absolute encoder); set speeds within the steering limits and a `timeout_ms` longer than the longest search; home once, read the angle the wheel stands at, write it as `steer_offset_rad`.
6. **EDS/DCF**: name the drive's EDS (or the DCF its vendor tool saved) in `[cia402.eds]`; `rollbase config check` then checks the boot plan against it (objects, access, ranges, PDO capacity) without a bus, and a DCF's values are written at every boot.
7. **Quick stop**: `[cia402.quick_stop]` `option` (0x605A; 2: quick-stop ramp then switch on disabled, 6: ramp then hold) and `drive_decel_rad_s2` / `steer_decel_rad_s2` (0x6085, at the joint): the drive stops on its own when the host loses its feedback. Check the ramp with the wheels lifted (cut a leg encoder's cable or power: the wheels must ramp down, not coast).
8. **Extra objects**: current limits, fault reaction (0x605E), brake, vendor objects as `[[cia402.sdo]]` (by `role` or `node`; `optional = true` for objects some drives lack). Mandatory objects a drive does not have fail the boot naming it: check the drive's EDS.
9. **Messages**: vendor notices (EMCY with error register 0) are informational; add codes a drive sends as warnings to `informational_emcy` only after reading its manual.
10. `rollbase config check platform.toml`, `rollbase bus-load --config platform.toml`, then `rollbase drive --bus can0 --commands -` with the wheels lifted: watch it boot, home and turn to rest; send small commands; `{"rearm": true}` clears a boot-time fault once its cause is fixed.

"#,
    );

    s.push_str("## Units (defaults)\n\n");
    let _ = writeln!(
        s,
        "| device | unit on the wire | SI |\n|---|---|---|\n\
         | rolling drive | position: increments ({} per motor revolution, gear {}); velocity: increments/s | 1 velocity unit = {:.3e} rad/s at the wheel |\n\
         | steering drive | position: increments ({} per motor revolution, gear {}); velocity: increments/s | 1 velocity unit = {:.3e} rad/s at the steering axis |\n\
         | leg encoder | position: {} nm steps (UNSIGNED32); speed: {} µm/s steps (INTEGER16) | λ = offset + position · step; up to {:.3} m/s |",
        cfg.drive.increments_per_rev,
        cfg.drive.gear_ratio,
        cfg.drive.velocity_resolution(),
        cfg.steer.increments_per_rev,
        cfg.steer.gear_ratio,
        cfg.steer.velocity_resolution(),
        cfg.leg_encoder.position_step_nm,
        cfg.leg_encoder.speed_step_um_s,
        cfg.leg_encoder.max_speed(),
    );
    s.push_str(
        "\nVelocity units `rpm` and `milli_rpm` (motor side) are also accepted \
         (`velocity_unit`). The steering angle is the position plus the wheel's \
         `steer_offset_rad` (its homing offset).\n\n",
    );

    s.push_str("## Bus load (`rollbase bus-load --profile cia402`)\n\n```text\n");
    let _ = writeln!(s, "{}", busload::load(&cfg, 4, 250.0, 1_000_000));
    s.push_str("```\n\n");
    s.push_str(
        "The cyclic load is above the native profile's 50 % budget: CANopen spends a frame per \
         drive and direction where the native module packs a wheel into one, and the drives' \
         TPDO1 carries both position and velocity. The headroom stays above a third of the bus \
         and the feedback burst ends inside the 2 ms window; more wheels, a slower bus or a \
         faster cycle do not fit (`rollbase bus-load --profile cia402 --config FILE` tells).\n",
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_every_object_of_the_plans() {
        let cfg = Cia402Config::for_wheels(4);
        for role in [Role::Drive, Role::Steer, Role::Leg] {
            for op in cfg.plan(role, 4000) {
                let (i, s) = op.object();
                assert_ne!(object_name(i, s), "object", "0x{i:04X}:{s:02X}");
            }
        }
        assert_eq!(object_name(0x1801, 3), "TPDO2 inhibit time");
        assert_eq!(object_name(0x1600, 2), "RPDO1 mapping entry 2");
    }
}
