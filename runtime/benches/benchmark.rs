//! `cargo bench -p softc`: the canonical benchmark table of `softc bench` (shared/BENCHMARK.md),
//! built with the release profile. Arguments after `--` are passed on, e.g.
//! `cargo bench -p softc -- --sizes 1k,10k --repeats 5`.

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the workspace root")
        .to_path_buf();
    let mut args: Vec<std::ffi::OsString> = vec![
        "softc".into(),
        "bench".into(),
        "--examples".into(),
        root.join("examples").into(),
    ];
    // cargo passes `--bench` to harness-less benches; it is not a softc flag.
    args.extend(std::env::args_os().skip(1).filter(|a| a != "--bench"));
    std::process::exit(softc::cli::main_with_args(args));
}
