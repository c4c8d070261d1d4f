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
    s.push_str("| # | object | name | operation |\n|---|---|---|---|\n");
    for (i, op) in cfg.plan(role, period_us).iter().enumerate() {
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
                ..
            } => format!("read, require value & 0x{mask:X} = 0x{expected:X}: {what}"),
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
         recording run on it; only the link changes (`control/src/link.rs`). The facts used \
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
         | SDO request | 0x600 + node | master → device | 8 | boot (configuration) |\n\
         | SDO response | 0x580 + node | device → master | 8 | boot |\n\
         | boot-up / heartbeat | 0x700 + node | device → all | 1 | boot-up once; heartbeat every `heartbeat_ms` |\n\
         | master heartbeat | 0x700 + master node | master → drives | 1 | every `master_heartbeat_ms` |\n\n",
    );
    s.push_str(
        "SDO transfers are expedited (every object the master reads or writes is at most 4 \
         bytes); a device answering with a segmented transfer fails the boot with a message \
         saying so.\n\n",
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
         and keeping it out of the cyclic TPDO keeps that at 8 bytes.\n\n",
    );

    s.push_str("## Boot\n\n");
    s.push_str(
        "For every device, in parallel: NMT reset communication → wait for its boot-up (at \
         most `boot_timeout_ms`) → the configuration below, one SDO request in flight per \
         device (at most two per cycle), each answered within `sdo_timeout_ms` or repeated \
         `sdo_retries` times → NMT start. The controller arms when every device runs. An abort, \
         a timeout or a value read back that does not match stops the boot; the run ends in \
         Fault with a message naming the node, its role, the object and the abort code. The \
         PDO COB-IDs below are written with the device's node-ID added.\n\n",
    );
    let _ = writeln!(
        s,
        "### Drives (rolling and steering), {} steps\n",
        cfg.plan(Role::Drive, period_us).len()
    );
    plan_table(&mut s, &cfg, Role::Drive, period_us);
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
         | EMCY with a non-zero code | master | device fault naming the code, controlled stop |\n\
         | statusword shows fault | master | device fault, controlled stop |\n\
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
         runs; only a fault still shown `enable_timeout_ms` later is reported.\n\n",
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
