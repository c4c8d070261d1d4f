//! docs/cia402.md must equal what the CiA 402 profile's tables generate.

use std::path::PathBuf;

#[test]
fn cia402_md_is_up_to_date() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../docs/cia402.md");
    let generated = rollbase_driver::canopen::doc::markdown();
    if std::env::var_os("UPDATE_DOCS").is_some_and(|v| v == "1") {
        std::fs::write(&path, &generated).expect("write docs/cia402.md");
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == generated,
        "docs/cia402.md is out of date with driver/src/canopen/: regenerate it with \
         `cargo run -- cia402-doc > docs/cia402.md` or \
         `UPDATE_DOCS=1 cargo test -p rollbase-driver --test cia402_doc`"
    );
}
