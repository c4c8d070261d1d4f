//! Motion commands as JSON Lines: the command files and the stdin stream of `rollbase drive`
//! and `rollbase demo --commands`.
//!
//! One JSON object per line:
//!
//! ```text
//! {"t": 1.25, "vx": 0.3, "vy": 0.0, "omega": 0.2}
//! {"t": 2.0, "vx": 0.3, "vy": 0.0, "omega": 0.2, "legs": [0.5, 0.5, 0.5, 0.5]}
//! {"t": 3.0, "legs": [0.45, 0.45, 0.45, 0.45]}
//! {"t": 9.0, "stop": true}
//! {"t": 12.0, "rearm": true}
//! ```
//!
//! - `t`: seconds since the driver was ready (it follows commands from then on); each line holds
//!   until the next, so a gap longer than the command timeout (`service.command_timeout`,
//!   0.5 s by default) lets the platform stop. Optional: a line without `t` takes effect as
//!   soon as it is read (for a live producer on stdin).
//! - `vx`, `vy` (m/s), `omega` (rad/s): the body twist in the base frame (REP 103: x forward,
//!   y left, z up). Give all three, or none (a line with only `legs`).
//! - `legs`: leg extension targets (m), one per wheel in the platform file's order.
//! - `stop: true`: a controlled stop; the platform then holds until `rearm: true`.
//! - `rearm: true`: clear latched faults whose cause is gone and follow commands again.
//!
//! Non-finite numbers are not JSON, but encoders write them anyway: Python's `json` as the
//! bare words `NaN`, `Infinity` and `-Infinity`, others (serde_json, nlohmann::json) as
//! `null`. A numeric field holding one of those (or the strings `"NaN"`, `"Infinity"`,
//! `"-Infinity"`) is read as that value, so the command port rejects the command, names the
//! field and counts it (`rejected_commands`) like any other non-finite command, instead of the
//! line being skipped as unreadable.
//!
//! Blank lines and lines starting with `#` are skipped. A line longer than
//! [`MAX_LINE_BYTES`] or that is not such an object is an error naming the line and the field.
//! The command port checks the values again (finite, within the sanity bounds, leg range)
//! when they arrive; those rejections are counted, not fatal.

use rollbase_control::service::ports::{CommandKind, LegTargets, MotionCommand};
use rollbase_control::types::Twist;
use std::io::{BufRead, Read};
use std::path::Path;

/// Longest accepted line (bytes).
pub const MAX_LINE_BYTES: usize = 4096;
/// Largest accepted command file (bytes).
pub const MAX_FILE_BYTES: u64 = 64 << 20;

/// A command line: what it asks, and when (s after the driver is ready; `None`: at once).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedCommand {
    /// When (s after the driver is ready), if given.
    pub t: Option<f64>,
    /// What.
    pub kind: CommandKind,
}

/// Why a command line or file was refused.
#[derive(Debug, thiserror::Error)]
pub enum CommandFileError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// The file is larger than [`MAX_FILE_BYTES`].
    #[error("{path}: {size} bytes is more than the {max} bytes a command file may have")]
    TooLarge {
        /// The file.
        path: String,
        /// Its size.
        size: u64,
        /// The cap.
        max: u64,
    },
    /// A line is wrong.
    #[error("{origin} line {line}: {message}")]
    Line {
        /// Where (`commands.jsonl` or `stdin`).
        origin: String,
        /// 1-based line number.
        line: usize,
        /// What is wrong and what is expected.
        message: String,
    },
}

fn line_error(source: &str, line: usize, message: impl Into<String>) -> CommandFileError {
    CommandFileError::Line {
        origin: source.into(),
        line,
        message: message.into(),
    }
}

/// The line with the bare words `NaN`, `Infinity` and `-Infinity` outside string literals
/// quoted (`"NaN"` …), so a JSON parser reads them; [`number`] turns them back into values.
/// Borrowed when there is none.
fn quote_non_finite(s: &str) -> std::borrow::Cow<'_, str> {
    const WORDS: [&str; 3] = ["-Infinity", "Infinity", "NaN"];
    if !WORDS.iter().any(|w| s.contains(w)) {
        return std::borrow::Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    let (mut in_string, mut escaped) = (false, false);
    let mut rest = s;
    while let Some(c) = rest.chars().next() {
        if in_string {
            if escaped {
                escaped = false;
            } else if c == '\\' {
                escaped = true;
            } else if c == '"' {
                in_string = false;
            }
        } else if c == '"' {
            in_string = true;
        } else if let Some(w) = WORDS.iter().find(|w| rest.starts_with(**w)) {
            let glued = |c: Option<char>| c.is_some_and(|c| c.is_alphanumeric() || c == '_');
            if !glued(out.chars().next_back()) && !glued(rest[w.len()..].chars().next()) {
                out.push('"');
                out.push_str(w);
                out.push('"');
                rest = &rest[w.len()..];
                continue;
            }
        }
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    std::borrow::Cow::Owned(out)
}

/// A numeric field's value: a JSON number, or a non-finite value as encoders write it
/// (`null`, `"NaN"`, `"Infinity"`, `"-Infinity"`; see the module docs).
fn number(x: &serde_json::Value) -> Option<f64> {
    match x {
        serde_json::Value::Number(n) => n.as_f64(),
        serde_json::Value::Null => Some(f64::NAN),
        serde_json::Value::String(s) => match s.as_str() {
            "NaN" => Some(f64::NAN),
            "Infinity" => Some(f64::INFINITY),
            "-Infinity" => Some(f64::NEG_INFINITY),
            _ => None,
        },
        _ => None,
    }
}

/// Start of the error [`UniqueKeys`] raises for a key given twice.
const DUPLICATE: &str = "duplicate key ";

/// A JSON value whose top-level object, if it is one, has no key twice (serde_json keeps
/// the last of equal keys without a word; which one a producer meant cannot be known).
struct UniqueKeys(serde_json::Value);

impl<'de> serde::Deserialize<'de> for UniqueKeys {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = serde_json::Value;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a JSON object")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut m: A,
            ) -> Result<Self::Value, A::Error> {
                let mut obj = serde_json::Map::new();
                while let Some(k) = m.next_key::<String>()? {
                    if obj.contains_key(&k) {
                        return Err(serde::de::Error::custom(format_args!("{DUPLICATE}`{k}`")));
                    }
                    let v: serde_json::Value = m.next_value()?;
                    obj.insert(k, v);
                }
                Ok(serde_json::Value::Object(obj))
            }
            // Anything else is read as it is; the caller says it is not an object.
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut a: A,
            ) -> Result<Self::Value, A::Error> {
                while a.next_element::<serde::de::IgnoredAny>()?.is_some() {}
                Ok(serde_json::Value::Array(Vec::new()))
            }
            fn visit_bool<E>(self, v: bool) -> Result<Self::Value, E> {
                Ok(serde_json::Value::Bool(v))
            }
            fn visit_i64<E>(self, v: i64) -> Result<Self::Value, E> {
                Ok(v.into())
            }
            fn visit_u64<E>(self, v: u64) -> Result<Self::Value, E> {
                Ok(v.into())
            }
            fn visit_f64<E>(self, v: f64) -> Result<Self::Value, E> {
                Ok(serde_json::json!(v))
            }
            fn visit_str<E>(self, v: &str) -> Result<Self::Value, E> {
                Ok(v.into())
            }
            fn visit_unit<E>(self) -> Result<Self::Value, E> {
                Ok(serde_json::Value::Null)
            }
        }
        d.deserialize_any(V).map(UniqueKeys)
    }
}

/// Parses one line (`source` and `line` name it in errors). `Ok(None)` for a blank or
/// comment line.
pub fn parse_line(
    text: &str,
    source: &str,
    line: usize,
) -> Result<Option<TimedCommand>, CommandFileError> {
    // A UTF-8 byte order mark (Windows editors write one) starts the stream, not the JSON.
    let text = match line {
        1 => text.strip_prefix('\u{feff}').unwrap_or(text),
        _ => text,
    };
    let s = text.trim();
    if s.is_empty() || s.starts_with('#') {
        return Ok(None);
    }
    if s.len() > MAX_LINE_BYTES {
        return Err(line_error(
            source,
            line,
            format!(
                "{} bytes is longer than the {MAX_LINE_BYTES} bytes a line may have",
                s.len()
            ),
        ));
    }
    let v: UniqueKeys = serde_json::from_str(&quote_non_finite(s)).map_err(|e| {
        let m = e.to_string();
        match m.strip_prefix(DUPLICATE) {
            Some(rest) => line_error(
                source,
                line,
                format!(
                    "field {} appears twice: give each field once",
                    rest.split(" at line").next().unwrap_or(rest)
                ),
            ),
            None => line_error(
                source,
                line,
                format!("not a JSON object ({e}); expected e.g. {{\"t\": 1.0, \"vx\": 0.2, \"vy\": 0.0, \"omega\": 0.1}}"),
            ),
        }
    })?;
    let obj = v.0.as_object().ok_or_else(|| {
        line_error(
            source,
            line,
            "not a JSON object: expected {\"t\": …, \"vx\": …, …}",
        )
    })?;
    for k in obj.keys() {
        if !matches!(
            k.as_str(),
            "t" | "vx" | "vy" | "omega" | "legs" | "stop" | "rearm"
        ) {
            return Err(line_error(
                source,
                line,
                format!("unknown field `{k}`: the fields are t, vx, vy, omega, legs, stop, rearm"),
            ));
        }
    }
    let num = |k: &str| -> Result<Option<f64>, CommandFileError> {
        match obj.get(k) {
            None => Ok(None),
            Some(x) => number(x).map(Some).ok_or_else(|| {
                line_error(source, line, format!("field `{k}` = {x} is not a number"))
            }),
        }
    };
    let flag = |k: &str| -> Result<bool, CommandFileError> {
        match obj.get(k) {
            None => Ok(false),
            Some(serde_json::Value::Bool(b)) => Ok(*b),
            Some(x) => Err(line_error(
                source,
                line,
                format!("field `{k}` = {x} is not true or false"),
            )),
        }
    };
    let t = num("t")?;
    if let Some(t) = t {
        if !(t.is_finite() && (0.0..=1e7).contains(&t)) {
            return Err(line_error(
                source,
                line,
                format!(
                    "field `t` = {t}: must be seconds after the driver is ready, between 0 and 1e7"
                ),
            ));
        }
    }
    let (stop, rearm) = (flag("stop")?, flag("rearm")?);
    let twist = (num("vx")?, num("vy")?, num("omega")?);
    let legs = match obj.get("legs") {
        None => None,
        Some(serde_json::Value::Array(a)) => {
            let mut l = Vec::with_capacity(a.len());
            for (i, x) in a.iter().enumerate() {
                l.push(number(x).ok_or_else(|| {
                    line_error(
                        source,
                        line,
                        format!("field `legs[{i}]` = {x} is not a number"),
                    )
                })?);
            }
            if l.len() > rollbase_control::types::MAX_WHEELS {
                return Err(line_error(
                    source,
                    line,
                    format!(
                        "field `legs` has {} entries; a platform has at most {}",
                        l.len(),
                        rollbase_control::types::MAX_WHEELS
                    ),
                ));
            }
            Some(LegTargets::from_slice(&l))
        }
        Some(x) => {
            return Err(line_error(
                source,
                line,
                format!("field `legs` = {x} is not an array of numbers (m)"),
            ))
        }
    };
    let motion = twist != (None, None, None);
    let kinds = [stop, rearm, motion || legs.is_some()]
        .iter()
        .filter(|x| **x)
        .count();
    if kinds != 1 {
        return Err(line_error(
            source,
            line,
            "a line holds one of: a twist (vx, vy, omega) with or without legs, legs alone, stop: true, or rearm: true",
        ));
    }
    let kind = if stop {
        CommandKind::Stop
    } else if rearm {
        CommandKind::Rearm
    } else if motion {
        let (Some(vx), Some(vy), Some(omega)) = twist else {
            return Err(line_error(
                source,
                line,
                "a twist needs all three of vx, vy and omega",
            ));
        };
        CommandKind::Motion(MotionCommand {
            twist: Twist { vx, vy, omega },
            legs,
        })
    } else {
        CommandKind::Legs(legs.unwrap_or_default())
    };
    Ok(Some(TimedCommand { t, kind }))
}

/// Reads a whole command file (at most [`MAX_FILE_BYTES`]); every line must parse and the
/// times must not go backwards. A file cannot stop the run early by itself: its end is the
/// end of the stream.
pub fn load_file(path: &Path) -> Result<Vec<TimedCommand>, CommandFileError> {
    let name = path.display().to_string();
    let io = |source| CommandFileError::Io {
        path: name.clone(),
        source,
    };
    let f = std::fs::File::open(path).map_err(io)?;
    let size = f.metadata().map_err(io)?.len();
    if size > MAX_FILE_BYTES {
        return Err(CommandFileError::TooLarge {
            path: name,
            size,
            max: MAX_FILE_BYTES,
        });
    }
    let mut out = Vec::new();
    let mut last_t = 0.0f64;
    let mut reader = std::io::BufReader::new(f.take(MAX_FILE_BYTES + 1));
    let mut buf = Vec::new();
    let mut line = 0;
    loop {
        buf.clear();
        let k = reader
            .by_ref()
            .take(MAX_LINE_BYTES as u64 + 2)
            .read_until(b'\n', &mut buf)
            .map_err(io)?;
        if k == 0 {
            break;
        }
        line += 1;
        if buf.len() > MAX_LINE_BYTES + 1 && !buf.ends_with(b"\n") {
            return Err(line_error(
                &name,
                line,
                format!("longer than the {MAX_LINE_BYTES} bytes a line may have"),
            ));
        }
        let text =
            std::str::from_utf8(&buf).map_err(|_| line_error(&name, line, "not UTF-8 text"))?;
        if let Some(c) = parse_line(text, &name, line)? {
            let t = c.t.unwrap_or(last_t);
            if t < last_t {
                return Err(line_error(
                    &name,
                    line,
                    format!("`t` = {t} goes back in time (the line before is at {last_t})"),
                ));
            }
            last_t = t;
            out.push(TimedCommand {
                t: Some(t),
                kind: c.kind,
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(s: &str) -> Result<Option<TimedCommand>, CommandFileError> {
        parse_line(s, "test", 3)
    }

    #[test]
    fn parses_every_kind_of_line() {
        let c = parse(r#"{"t": 1.25, "vx": 0.3, "vy": 0.0, "omega": 0.2}"#)
            .unwrap()
            .unwrap();
        assert_eq!(c.t, Some(1.25));
        assert!(matches!(c.kind, CommandKind::Motion(m) if m.twist.vx == 0.3 && m.legs.is_none()));
        let c = parse(r#"{"vx": 0.1, "vy": 0.2, "omega": 0, "legs": [0.4, 0.5, 0.4, 0.5]}"#)
            .unwrap()
            .unwrap();
        assert_eq!(c.t, None);
        assert!(
            matches!(c.kind, CommandKind::Motion(m) if m.legs.unwrap().as_slice() == [0.4, 0.5, 0.4, 0.5])
        );
        assert!(matches!(
            parse(r#"{"t": 2, "legs": [0.4, 0.4]}"#).unwrap().unwrap().kind,
            CommandKind::Legs(l) if l.n == 2
        ));
        assert!(matches!(
            parse(r#"{"t": 3, "stop": true}"#).unwrap().unwrap().kind,
            CommandKind::Stop
        ));
        assert!(matches!(
            parse(r#"{"rearm": true}"#).unwrap().unwrap().kind,
            CommandKind::Rearm
        ));
        assert!(parse("   ").unwrap().is_none());
        assert!(parse("# a comment").unwrap().is_none());
    }

    #[test]
    fn errors_name_the_line_and_the_field() {
        let e = |s: &str| parse(s).unwrap_err().to_string();
        assert!(
            e(r#"{"t": 1, "vx": "fast", "vy": 0, "omega": 0}"#).contains("test line 3: field `vx`")
        );
        assert!(e(r#"{"t": 1, "vx": 1, "vy": 0}"#).contains("all three"));
        assert!(e(r#"{"t": 1, "speed": 1}"#).contains("unknown field `speed`"));
        assert!(e(r#"{"t": -1, "stop": true}"#).contains("`t` = -1"));
        assert!(e(r#"{"t": 1, "stop": true, "vx": 1, "vy": 0, "omega": 0}"#).contains("one of"));
        assert!(e(r#"{"t": 1, "legs": [0.4, "x"]}"#).contains("legs[1]"));
        assert!(e("[1, 2]").contains("not a JSON object"));
        assert!(e("{nope").contains("not a JSON object"));
        let long = format!(r#"{{"t": 1, "stop": true, "pad": "{}"}}"#, "x".repeat(5000));
        assert!(e(&long).contains("longer than"));
    }

    #[test]
    fn non_finite_values_as_encoders_write_them_reach_the_command_port() {
        let twist = |s: &str| match parse(s).unwrap().unwrap().kind {
            CommandKind::Motion(m) => m.twist,
            k => panic!("{k:?}"),
        };
        // Python's json.dumps(float("nan")) and float("inf").
        assert!(twist(r#"{"t": 1, "vx": NaN, "vy": 0.0, "omega": 0.0}"#)
            .vx
            .is_nan());
        let t = twist(r#"{"vx": Infinity, "vy": -Infinity, "omega": 0}"#);
        assert_eq!((t.vx, t.vy), (f64::INFINITY, f64::NEG_INFINITY));
        // serde_json and nlohmann::json write NaN as null.
        assert!(twist(r#"{"vx": 0, "vy": null, "omega": 0}"#).vy.is_nan());
        assert!(twist(r#"{"vx": 0, "vy": 0, "omega": "NaN"}"#)
            .omega
            .is_nan());
        assert!(matches!(
            parse(r#"{"legs": [0.4, NaN, 0.4, 0.4]}"#).unwrap().unwrap().kind,
            CommandKind::Legs(l) if l.as_slice()[1].is_nan()
        ));
        // The port rejects them, naming the field.
        let p = rollbase_control::Platform::justin();
        let m = match parse(r#"{"vx": 0.1, "vy": NaN, "omega": 0}"#)
            .unwrap()
            .unwrap()
            .kind
        {
            CommandKind::Motion(m) => m,
            k => panic!("{k:?}"),
        };
        let e = rollbase_control::service::command::check_motion(&p, &m).unwrap_err();
        assert!(e.to_string().contains("`vy` is NaN"), "{e}");
        // Only bare words outside strings, never a field name, a word inside another or `t`.
        assert!(parse(r#"{"t": NaN, "stop": true}"#)
            .unwrap_err()
            .to_string()
            .contains("`t` = NaN"));
        assert!(parse(r#"{"vx": NaNa, "vy": 0, "omega": 0}"#)
            .unwrap_err()
            .to_string()
            .contains("not a JSON object"));
        assert!(parse(r#"{"NaN": 1}"#)
            .unwrap_err()
            .to_string()
            .contains("unknown field `NaN`"));
        assert!(parse(r#"{"vx": "fast", "vy": 0, "omega": 0}"#).is_err());
        assert!(parse(r#"{"stop": null}"#).is_err());
    }

    #[test]
    fn a_byte_order_mark_before_the_first_line_is_skipped() {
        // Windows editors (Notepad, PowerShell's `Out-File -Encoding utf8`) start a UTF-8 file
        // with U+FEFF; it is not part of the first line's JSON.
        let c = parse_line("\u{feff}{\"t\": 1, \"stop\": true}", "f", 1)
            .unwrap()
            .unwrap();
        assert_eq!((c.t, c.kind), (Some(1.0), CommandKind::Stop));
        let dir = std::env::temp_dir().join(format!("rollbase-bom-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("c.jsonl");
        std::fs::write(
            &p,
            "\u{feff}{\"t\": 0, \"vx\": 0.1, \"vy\": 0, \"omega\": 0}\n{\"t\": 1, \"stop\": true}\n",
        )
        .unwrap();
        assert_eq!(load_file(&p).unwrap().len(), 2);
        // Only before the first line: elsewhere it is a character that is not JSON.
        assert!(parse_line("\u{feff}{\"t\": 1, \"stop\": true}", "f", 2).is_err());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_field_given_twice_is_refused_naming_it() {
        // serde_json keeps the last of two equal keys; which one the producer meant is
        // unknowable, so the line is refused.
        let e = parse(r#"{"t": 1, "vx": 0.1, "vy": 0, "omega": 0, "vx": 2.0}"#)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("test line 3") && e.contains("`vx` appears twice"),
            "{e}"
        );
        let e = parse(r#"{"stop": true, "stop": false}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("`stop` appears twice"), "{e}");
        // Equal keys in different objects are not duplicates (and keys are compared exactly).
        assert!(parse(r#"{"t": 1, "vx": 0.1, "vy": 0, "omega": 0}"#).is_ok());
    }

    #[test]
    fn a_file_is_read_whole_with_line_numbers_and_bounded() {
        let dir = std::env::temp_dir().join(format!("rollbase-cmds-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("c.jsonl");
        std::fs::write(
            &p,
            "# drive\n{\"t\": 0, \"vx\": 0.2, \"vy\": 0, \"omega\": 0}\n\n{\"vx\": 0, \"vy\": 0, \"omega\": 0}\n{\"t\": 2.5, \"stop\": true}\n",
        )
        .unwrap();
        let v = load_file(&p).unwrap();
        assert_eq!(v.len(), 3);
        assert_eq!(
            v[1].t,
            Some(0.0),
            "a line without t takes the time before it"
        );
        std::fs::write(
            &p,
            "{\"t\": 2, \"stop\": true}\n{\"t\": 1, \"stop\": true}\n",
        )
        .unwrap();
        assert!(load_file(&p)
            .unwrap_err()
            .to_string()
            .contains("line 2: `t` = 1 goes back"));
        std::fs::write(&p, [b'{', 0xFF, b'}', b'\n']).unwrap();
        assert!(load_file(&p)
            .unwrap_err()
            .to_string()
            .contains("line 1: not UTF-8"));
        // An endless line (think /dev/zero) stops at the cap instead of eating memory.
        std::fs::write(&p, vec![b'x'; MAX_LINE_BYTES * 3]).unwrap();
        assert!(load_file(&p)
            .unwrap_err()
            .to_string()
            .contains("line 1: longer than"));
        let _ = std::fs::remove_dir_all(dir);
    }
}
