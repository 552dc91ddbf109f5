//! The `softc` binary. Arguments are read as OS strings (`args_os`): `std::env::args` panics
//! on an argument that is not UTF-8.

fn main() {
    let code = softc::cli::main_with_args(std::env::args_os().collect());
    std::process::exit(code);
}
