fn main() {
    println!("rollbase");
}
