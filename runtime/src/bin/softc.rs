fn main() {
    let code = softc::cli::main_with_args(std::env::args().collect());
    std::process::exit(code);
}
