//! Fuzz target: the platform description parser (`Platform::from_toml_str`).
//!
//! Any input must give `Ok` or an error, never a panic. A platform that parses must pass
//! `validate()` again and must round-trip through `to_toml_string` to an equal platform.
//!
//! Run: `cargo +nightly fuzz run platform_toml` from the repository root.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rollbase_control::Platform;

fuzz_target!(|input: &[u8]| {
    let Ok(text) = std::str::from_utf8(input) else {
        return;
    };
    if let Ok(p) = Platform::from_toml_str(text) {
        p.validate().expect("a parsed platform is valid");
        let again = Platform::from_toml_str(&p.to_toml_string())
            .expect("a valid platform's TOML must parse again");
        assert_eq!(p, again);
    }
});
