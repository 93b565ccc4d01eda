// `sqlx::migrate!` embeds migrations/{sqlite,postgres} at compile time; rebuild when a migration is added.
fn main() {
    println!("cargo:rerun-if-changed=../../migrations");
}
