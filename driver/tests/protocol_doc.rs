//! docs/protocol.md must equal what the table generates.

use std::path::PathBuf;

#[test]
fn protocol_md_is_up_to_date() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../docs/protocol.md");
    let generated = rollbase_driver::dbc::protocol_markdown();
    if std::env::var_os("UPDATE_DOCS").is_some_and(|v| v == "1") {
        std::fs::write(&path, &generated).expect("write docs/protocol.md");
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == generated,
        "docs/protocol.md is out of date with driver/src/protocol.rs: regenerate it with \
         `cargo run -- protocol-doc > docs/protocol.md` or \
         `UPDATE_DOCS=1 cargo test -p rollbase-driver --test protocol_doc`"
    );
}
