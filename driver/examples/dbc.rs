//! Prints the DBC (`cargo run -p rollbase-driver --example dbc > rollbase.dbc`).
fn main() {
    print!("{}", rollbase_driver::dbc::dbc());
}
