//! The crate's one error enum.

use rollbase_driver::BusError;

/// Everything that can go wrong in the simulator: bad configuration (plant, fault schedule,
/// initial state, command-line fault options), unreadable files, and bus failures in the
/// real-time loop. Messages name the offending field or value and say what to do.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A configuration field has an unacceptable value.
    #[error("`{field}` = {value}: {reason}")]
    Invalid {
        /// Dotted path of the field, e.g. `plant.drive_time_constant`, `silent[1].to`,
        /// `--encoder-jump`.
        field: String,
        /// The offending value, printed.
        value: String,
        /// What is wrong and what is expected.
        reason: String,
    },
    /// A TOML file (or string) is malformed, has an unknown key or a value of the wrong type.
    /// The message from the TOML parser names the key and the line.
    #[error("{what} is not valid: {message}")]
    Parse {
        /// What was being parsed, e.g. `plant file plant.toml`.
        what: String,
        /// The parser's message (names the unknown/bad key and its position).
        message: String,
    },
    /// A file could not be read, is too large (`/dev/zero` …) or is not UTF-8 text.
    #[error(transparent)]
    Input(#[from] rollbase_driver::input::InputError),
    /// The platform description is invalid.
    #[error(transparent)]
    Platform(#[from] rollbase_control::ConfigError),
    /// The bus failed in a way that cannot be retried (interface down, bus off, closed …).
    #[error("bus error: {0}")]
    Bus(#[from] BusError),
}

/// Shorthand for [`SimError::Invalid`].
pub(crate) fn invalid(
    field: impl Into<String>,
    value: impl std::fmt::Display,
    reason: impl Into<String>,
) -> SimError {
    SimError::Invalid {
        field: field.into(),
        value: value.to_string(),
        reason: reason.into(),
    }
}

/// Reads a whole TOML configuration file (`what`: "plant file", "fault file"), at most
/// [`rollbase_driver::input::MAX_CONFIG_BYTES`] long, mapping the error to [`SimError::Input`].
pub(crate) fn read_file(path: &std::path::Path, what: &'static str) -> Result<String, SimError> {
    Ok(rollbase_driver::input::read_text(
        path,
        rollbase_driver::input::MAX_CONFIG_BYTES,
        what,
    )?)
}
