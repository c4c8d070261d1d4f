//! The boot plan checked against device description files (CiA 306 EDS/DCF) before any
//! frame is sent. The fixtures in tests/eds/ are written by interop/cia402_eds.py (the
//! independent device set's EDS, from the standards): a good drive and encoder, and broken
//! drives with one change each (missing object, read-only object, value out of range,
//! unmappable object), and a DCF with configured values.

use rollbase_driver::canopen::config::{Cia402Config, EdsDevice, ExtraSdo, Role, SdoOp};
use rollbase_driver::canopen::eds::{self, DcfSkip, EdsError, PlanProblem};
use std::path::{Path, PathBuf};

const PERIOD_US: u32 = 4000;

fn dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/eds")
}

/// Four wheels, every rolling and steering drive described by `drive`, encoders by
/// encoder.eds.
fn config(drive: &str) -> Cia402Config {
    let mut c = Cia402Config::for_wheels(4);
    c.eds.drive = Some(drive.into());
    c.eds.steer = Some("drive.eds".into());
    c.eds.leg = Some("encoder.eds".into());
    c.validate(4, 250.0).expect("valid");
    c
}

fn plan_error(c: &mut Cia402Config) -> (String, u8, u16, u8, PlanProblem, String) {
    match eds::apply(c, &dir(), PERIOD_US) {
        Err(e @ EdsError::Plan { .. }) => {
            let text = e.to_string();
            let EdsError::Plan {
                path,
                node,
                index,
                sub,
                problem,
                ..
            } = e
            else {
                unreachable!()
            };
            (path, node, index, sub, problem, text)
        }
        r => panic!("expected a plan error, got {r:?}"),
    }
}

#[test]
fn the_boot_plan_fits_the_independent_devices_descriptions() {
    let mut c = config("drive.eds");
    let report = eds::apply(&mut c, &dir(), PERIOD_US).expect("the plan fits");
    // Every device checked, with its file and product.
    assert_eq!(report.devices.len(), 12);
    for (node, role, path, product, dcf) in &report.devices {
        let want = if *role == Role::Leg {
            "encoder.eds"
        } else {
            "drive.eds"
        };
        assert!(path.ends_with(want), "node {node}: {path}");
        assert!(!product.is_empty());
        assert_eq!(*dcf, 0, "an EDS has no values to write");
    }
    assert!(c.dcf.is_empty());
}

#[test]
fn a_missing_object_is_refused_naming_the_device_object_and_file() {
    let mut c = config("missing-6060.eds");
    let (path, node, index, sub, problem, text) = plan_error(&mut c);
    assert_eq!((node, index, sub), (1, 0x6060, 0));
    assert!(path.ends_with("missing-6060.eds"), "{path}");
    assert!(matches!(
        problem,
        PlanProblem::Missing {
            write: true,
            extra: false
        }
    ));
    for needle in [
        "node 1",
        "rolling drive",
        "0x6060:00",
        "missing-6060.eds",
        "right file",
    ] {
        assert!(text.contains(needle), "{needle:?} not in: {text}");
    }
    println!("{text}");
}

#[test]
fn a_read_only_object_the_plan_writes_is_refused() {
    let mut c = config("readonly-6007.eds");
    let (_, node, index, _, problem, text) = plan_error(&mut c);
    assert_eq!((node, index), (1, 0x6007));
    assert!(
        matches!(problem, PlanProblem::NotWritable { access: "ro", .. }),
        "{problem:?}"
    );
    assert!(
        text.contains("0x6007:00") && text.contains("`ro`"),
        "{text}"
    );
    println!("{text}");
}

#[test]
fn a_value_outside_the_objects_limits_is_refused() {
    // The fixture's 0x6007 allows up to 0; the plan writes the platform's reaction, 1.
    let mut c = config("range-6007.eds");
    let (_, node, index, _, problem, text) = plan_error(&mut c);
    assert_eq!((node, index), (1, 0x6007));
    assert_eq!(
        problem,
        PlanProblem::OutOfRange {
            value: 1,
            low: Some(-32768),
            high: Some(0)
        }
    );
    assert!(text.contains("-32768..=0"), "{text}");
    // The same file takes a reaction within its range.
    let mut c = config("range-6007.eds");
    c.comm_loss_reaction = 0;
    assert!(eds::apply(&mut c, &dir(), PERIOD_US).is_ok());
}

#[test]
fn an_object_mapped_that_the_device_cannot_map_is_refused() {
    let mut c = config("unmappable-6041.eds");
    let (_, node, index, sub, problem, text) = plan_error(&mut c);
    assert_eq!((node, index, sub), (1, 0x6041, 0));
    assert!(
        matches!(
            problem,
            PlanProblem::NotMappable {
                map_index: 0x1A01,
                ..
            }
        ),
        "{problem:?}"
    );
    // The statusword goes in TPDO2 (event-driven).
    assert!(text.contains("TPDO2"), "{text}");
}

/// A copy of the fixtures in a fresh directory, with drive.eds changed by `edit` and saved
/// as `name`; removed when dropped.
struct Edited(PathBuf);

impl Edited {
    fn new(name: &str, edit: impl Fn(&str) -> String) -> Self {
        let text = std::fs::read_to_string(dir().join("drive.eds")).expect("fixture");
        let changed = edit(&text);
        assert_ne!(changed, text, "fixture layout changed");
        let tmp = std::env::temp_dir().join(format!("rollbase-eds-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&tmp).expect("tmp");
        std::fs::write(tmp.join(name), changed).expect("write");
        for f in ["drive.eds", "encoder.eds"] {
            std::fs::copy(dir().join(f), tmp.join(f)).expect("copy");
        }
        Self(tmp)
    }
}

impl Drop for Edited {
    fn drop(&mut self) {
        std::fs::remove_dir_all(&self.0).ok();
    }
}

#[test]
fn more_mapped_objects_than_the_mapping_object_holds_are_refused() {
    // A drive whose status TPDO (TPDO2, 0x1A01) maps one object at most: the statusword
    // fits, the statusword and the error code 0x603F do not.
    let tmp = Edited::new("one-entry.eds", |t| {
        t.replace(
            "[1A01]\nParameterName=Object 0x1A01\nObjectType=0x9\nSubNumber=9\n",
            "[1A01]\nParameterName=Object 0x1A01\nObjectType=0x9\nSubNumber=2\n",
        )
        .split("\n[")
        .filter(|section| !(2..=8).any(|k| section.starts_with(&format!("1A01sub{k}]"))))
        .collect::<Vec<_>>()
        .join("\n[")
    });
    let mut c = config("one-entry.eds");
    c.eds.steer = Some("one-entry.eds".into());
    assert!(eds::apply(&mut c, &tmp.0, PERIOD_US).is_ok());
    c.status_extra = vec![0x603F_0010];
    c.validate(4, 250.0).expect("valid platform");
    let e = eds::apply(&mut c, &tmp.0, PERIOD_US).expect_err("too many");
    let t = e.to_string();
    match e {
        EdsError::Plan {
            node: 1,
            index: 0x1A01,
            problem:
                PlanProblem::Capacity {
                    entries: 2,
                    max_entries: 1,
                    ..
                },
            ..
        } => {}
        _ => panic!("{t}"),
    }
    assert!(t.contains("TPDO2") && t.contains("status_extra"), "{t}");
    println!("{t}");
}

#[test]
fn an_extra_sdo_entry_the_device_lacks_says_to_remove_it_or_mark_it_optional() {
    let mut c = config("drive.eds");
    c.sdo = vec![ExtraSdo {
        role: None,
        node: Some(3),
        index: 0x2101,
        sub: 0,
        value: 5,
        size: 2,
        optional: false,
    }];
    let (_, node, index, _, problem, text) = plan_error(&mut c);
    assert_eq!((node, index), (3, 0x2101));
    assert!(matches!(
        problem,
        PlanProblem::Missing {
            write: true,
            extra: true
        }
    ));
    assert!(text.contains("[[cia402.sdo]]") && text.contains("optional = true"));
    // Marked optional, the boot would skip it (the device answers "object does not exist").
    c.sdo[0].optional = true;
    assert!(eds::apply(&mut c, &dir(), PERIOD_US).is_ok());
}

#[test]
fn a_dcfs_values_are_written_after_the_plans_defaults_and_before_the_platform_files_list() {
    let mut c = config("drive.eds");
    // One device gets its own DCF.
    c.eds.devices = vec![EdsDevice {
        node: 3,
        file: "drive.dcf".into(),
    }];
    c.sdo = vec![ExtraSdo {
        role: None,
        node: Some(3),
        index: 0x6085,
        sub: 0,
        value: 123_456,
        size: 4,
        optional: false,
    }];
    let report = eds::apply(&mut c, &dir(), PERIOD_US).expect("fits");
    let (_, _, path, _, n) = report
        .devices
        .iter()
        .find(|d| d.0 == 3)
        .expect("node 3 checked");
    assert!(path.ends_with("drive.dcf"), "{path}");
    assert_eq!(*n, 2, "0x605A and 0x6085");
    // 0x6041 (read-only) is not written, and said so.
    assert!(report
        .skipped
        .contains(&(3, 0x6041, 0, DcfSkip::NotWritable)));
    let writes = |node: u8| -> Vec<(u16, u32)> {
        c.plan_for(1, Role::Drive, PERIOD_US)
            .iter()
            .filter_map(
                |op| match rollbase_driver::canopen::config::for_node(*op, node) {
                    SdoOp::Write {
                        index,
                        sub: 0,
                        data,
                        ..
                    } if index == 0x605A || index == 0x6085 => Some((index, data.as_u32())),
                    _ => None,
                },
            )
            .collect()
    };
    // Node 3 (wheel 2's rolling drive): the plan's default option 2, the DCF's 6; the
    // plan's deceleration, the DCF's 200000, the platform file's 123456 last.
    let w = writes(3);
    let qs: Vec<u32> = w.iter().filter(|x| x.0 == 0x605A).map(|x| x.1).collect();
    assert_eq!(qs, vec![2, 6], "{w:x?}");
    let dec: Vec<u32> = w.iter().filter(|x| x.0 == 0x6085).map(|x| x.1).collect();
    assert_eq!(dec.len(), 3, "{w:x?}");
    assert_eq!(&dec[1..], &[200_000, 123_456], "{w:x?}");
    // Another drive has no DCF values.
    assert!(c.dcf.iter().all(|d| d.node == 3));
}

#[test]
fn a_dcf_configuring_another_encoder_resolution_than_the_platform_file_is_refused_ahead() {
    // 0x608F:01 configured to 4096 increments; the platform file says 16384.
    let tmp = Edited::new("res.dcf", |t| {
        t.replace(
            "ParameterName=Encoder increments\n",
            "ParameterName=Encoder increments\nParameterValue=4096\n",
        )
    });
    let mut c = config("res.dcf");
    c.eds.steer = Some("res.dcf".into());
    let r = eds::apply(&mut c, &tmp.0, PERIOD_US);
    let e = r.expect_err("mismatch");
    let t = e.to_string();
    assert!(
        matches!(
            e,
            EdsError::Plan {
                index: 0x608F,
                sub: 1,
                problem: PlanProblem::DcfMismatch {
                    dcf: 4096,
                    expected: 16384,
                    ..
                },
                ..
            }
        ),
        "{t}"
    );
    println!("{t}");
}

#[test]
fn a_missing_or_malformed_file_names_the_file() {
    let mut c = config("nope.eds");
    let e = eds::apply(&mut c, &dir(), PERIOD_US).expect_err("missing");
    assert!(e.to_string().contains("nope.eds"), "{e}");
    let e = eds::Eds::parse("[DeviceInfo]\n[1000]\nAccessType=xx\n", "x.eds").expect_err("bad");
    assert!(e.to_string().contains("x.eds"), "{e}");
}
