//! The `softc` command line.
//!
//! Exit status: 0 success, 1 a problem in the user's input (script, mesh), 2 a usage error
//! (bad flags, unreadable file, a command that is not implemented yet).

pub mod bench;
pub mod mesh;
pub mod optimize;
pub mod run;

// Through here, not from each other: `softc run` hands a script with an `optimize` block to
// the optimization, which reads the same flags; every command writes files atomically.
use crate::outputs::atomic::write_atomically;
pub use optimize::optimize;
pub use run::RunArgs;

use crate::devices::{BackendChoice, PrecisionChoice};
use clap::{Parser, Subcommand, ValueEnum};
use softc_compiler::CheckOptions;
use softc_compiler::diag::{Diagnostic, SourceFile};
use std::ffi::{OsStr, OsString};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

#[derive(Parser, Debug)]
#[command(
    name = "softc",
    version,
    about = "Compiler and runtime for differentiable simulation of soft pressure actuators",
    long_about = None
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Check scripts for errors without running them.
    Check {
        /// Scripts to check (`-` reads standard input).
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// How to print diagnostics.
        #[arg(long, value_enum, default_value_t = MessageFormat::Human)]
        message_format: MessageFormat,
        /// Treat warnings as errors (exit status 1).
        #[arg(long)]
        deny_warnings: bool,
    },
    /// Format scripts in place (canonical layout, comments kept).
    Fmt {
        /// Scripts to format (`-` formats standard input to standard output).
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Do not write; exit with status 1 if a file is not formatted.
        #[arg(long)]
        check: bool,
    },
    /// Compile a script and print its kernels.
    Compile {
        file: PathBuf,
        /// What to print: the kernel IR, the Cranelift IR of the CPU backend, or the WGSL of the
        /// GPU backend.
        #[arg(long, value_enum, default_value_t = Emit::Ir)]
        emit: Emit,
        /// Precision of `--emit wgsl` (default: the script's `precision` setting, else f32).
        #[arg(long, value_enum)]
        precision: Option<PrecisionChoice>,
        /// `--emit wgsl` for a batch of this many scenes run in one dispatch (what `softc run
        /// --backend gpu` uses when an optimization evaluates several scenes per iteration).
        #[arg(long, value_name = "SCENES")]
        batch: Option<u32>,
    },
    /// Simulate a script and print a JSON summary (optimization comes with the adjoint).
    Run(RunArgs),
    /// Forward speed of every backend on the canonical benchmark scene (table, `--json`).
    Bench(bench::BenchArgs),
    /// Generate, inspect and convert tetrahedral meshes.
    Mesh {
        #[command(subcommand)]
        command: mesh::MeshCommand,
    },
    /// Run the language server on standard input/output (editors start it).
    Lsp,
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum Emit {
    /// The kernel IR of every kernel of the scene.
    Ir,
    /// Cranelift IR of the CPU backend (f64).
    Clif,
    /// WGSL of the GPU backend (f32 unless `--precision f64` or the script says `precision f64`),
    /// validated with naga.
    Wgsl,
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum MessageFormat {
    /// `FILE:LINE:COL: error[CODE]: message`, the source line, and a hint.
    Human,
    /// One JSON object per diagnostic and line, for editors and tools.
    Json,
}

/// Run the command line with explicit output streams (tests call this in-process). Arguments
/// are OS strings: a file name or flag value that is not UTF-8 is a usage error with a message,
/// never a panic.
pub fn run<A: AsRef<OsStr>>(args: &[A], out: &mut dyn Write, err: &mut dyn Write) -> i32 {
    let cli = match Cli::try_parse_from(args.iter().map(|a| a.as_ref().to_os_string())) {
        Ok(cli) => cli,
        Err(e) if e.kind() == clap::error::ErrorKind::InvalidUtf8 => {
            // clap does not say which argument: name it (lossily) and where it may go.
            let bad = args
                .iter()
                .enumerate()
                .skip(1)
                .find(|(_, a)| a.as_ref().to_str().is_none());
            let which = bad.map_or(String::new(), |(i, a)| {
                format!(" (argument {i}: `{}`)", a.as_ref().to_string_lossy())
            });
            let _ = writeln!(
                err,
                "softc: a command, flag or value is not valid UTF-8{which}; only file names may \
                 be arbitrary bytes: write names and values in UTF-8 (see `softc --help`)"
            );
            return 2;
        }
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let _ = if e.use_stderr() {
                write!(err, "{e}")
            } else {
                write!(out, "{e}")
            };
            return code;
        }
    };
    match cli.command {
        Command::Check {
            files,
            message_format,
            deny_warnings,
        } => check_files(&files, message_format, deny_warnings, out, err),
        Command::Fmt { files, check } => fmt_files(&files, check, out, err),
        Command::Compile {
            file,
            emit,
            precision,
            batch,
        } => compile_file(&file, emit, precision, batch, out, err),
        Command::Run(args) => run::run(args, out, err),
        Command::Bench(args) => bench::run(args, out, err),
        Command::Mesh {
            command:
                mesh::MeshCommand::Converge {
                    script,
                    orders,
                    resolutions,
                    output,
                    set,
                    threads,
                    out: folder,
                },
        } => bench::mesh_converge(
            &script,
            &orders,
            &resolutions,
            &output,
            &set,
            threads,
            &folder,
            out,
            err,
        ),
        Command::Mesh { command } => mesh::run(command, out, err),
        Command::Lsp => crate::lsp::run_stdio(),
    }
}

/// Entry point of the binary: runs the front end on a thread with a large stack, so that even
/// pathological scripts (deep nesting near the parser's limits) cannot overflow it.
pub fn main_with_args<A: Into<OsString>>(args: Vec<A>) -> i32 {
    let args: Vec<OsString> = args.into_iter().map(Into::into).collect();
    let worker = std::thread::Builder::new()
        .name("softc".into())
        .stack_size(64 << 20)
        .spawn(move || {
            let stdout = std::io::stdout();
            let stderr = std::io::stderr();
            run(&args, &mut stdout.lock(), &mut stderr.lock())
        });
    match worker.map(|h| h.join()) {
        Ok(Ok(code)) => code,
        _ => {
            eprintln!(
                "softc: internal error (this is a bug in softc; please report it with the input)"
            );
            101
        }
    }
}

/// Read a file (or standard input for `-`), reporting failures as usage errors.
fn read_input(path: &Path, err: &mut dyn Write) -> Option<Vec<u8>> {
    let result = if path == Path::new("-") {
        let mut buf = Vec::new();
        std::io::stdin().read_to_end(&mut buf).map(|_| buf)
    } else {
        crate::files::read_regular(path)
    };
    match result {
        Ok(b) => Some(b),
        Err(e) => {
            let _ = writeln!(err, "softc: cannot read `{}`: {e}", path.display());
            None
        }
    }
}

fn display_name(path: &Path) -> String {
    if path == Path::new("-") {
        "<stdin>".into()
    } else {
        path.display().to_string()
    }
}

fn check_files(
    files: &[PathBuf],
    format: MessageFormat,
    deny_warnings: bool,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    let mut status = 0;
    for path in files {
        let Some(bytes) = read_input(path, err) else {
            status = 2;
            continue;
        };
        let options = check_options(path);
        let (text, checked) = softc_compiler::check_bytes(&bytes, &options);
        let name = display_name(path);
        let file = SourceFile::new(&name, &text);
        report(&file, &checked.diagnostics, format, out, err);
        let errors = checked.diagnostics.iter().filter(|d| d.is_error()).count();
        let warnings = checked.diagnostics.len() - errors;
        if format == MessageFormat::Human {
            let summary = match (errors, warnings) {
                (0, 0) => format!("{name}: ok"),
                (0, w) => format!("{name}: ok, {w} warning{}", plural(w)),
                (e, 0) => format!("{name}: {e} error{}", plural(e)),
                (e, w) => format!("{name}: {e} error{}, {w} warning{}", plural(e), plural(w)),
            };
            let _ = writeln!(err, "{summary}");
        }
        if (errors > 0 || (deny_warnings && warnings > 0)) && status == 0 {
            status = 1;
        }
    }
    status
}

/// The options `check` and `compile` use for a script file.
fn check_options(path: &Path) -> CheckOptions {
    CheckOptions {
        mesh_probe: Some(std::sync::Arc::new(crate::mesh::probe::FileProbe)),
        base_dir: if path == Path::new("-") {
            std::env::current_dir().ok()
        } else {
            let dir = path
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
                .unwrap_or(Path::new("."));
            Some(dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf()))
        },
    }
}

fn compile_file(
    path: &Path,
    emit: Emit,
    precision: Option<PrecisionChoice>,
    batch: Option<u32>,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    if (precision.is_some() || batch.is_some()) && emit != Emit::Wgsl {
        let _ = writeln!(
            err,
            "softc compile: --precision and --batch apply to --emit wgsl"
        );
        return 2;
    }
    let Some(bytes) = read_input(path, err) else {
        return 2;
    };
    let name = display_name(path);
    let check = check_options(path);
    let options = softc_compiler::CompileOptions {
        base_dir: check.base_dir,
        mesh_probe: check.mesh_probe,
        ..Default::default()
    };
    let compiled = softc_compiler::compile(&name, &bytes, &options);
    if let Err(f) = &compiled
        && f.lowering.is_none()
    {
        let file = SourceFile::new(&name, &f.text);
        report(&file, &f.diagnostics, MessageFormat::Human, out, err);
        let _ = writeln!(err, "{name}: not compiled (fix the errors first)");
        return 1;
    }
    match compiled.map(|c| (c.kernels, c.program)) {
        Ok((scene, _)) if emit == Emit::Clif => {
            match softc_compiler::back::cranelift::CpuModule::compile(
                &scene.adjoint.module,
                softc_compiler::back::Precision::F64,
            ) {
                Ok(m) => {
                    let _ = write!(out, "{}", m.clif_all());
                    // The time loop over one forward step's kernels (element, pressure, node).
                    let step: Vec<usize> =
                        (0..scene.materials.len() + scene.chambers.len() + 1).collect();
                    match m.compile_loop(&step) {
                        Ok(lp) => {
                            let _ = write!(
                                out,
                                "\n; time loop: n steps of kernels {step:?}, t and the state \
                                 buffers' parity set per step\n{}",
                                lp.clif
                            );
                            0
                        }
                        Err(e) => {
                            let _ = writeln!(err, "{name}: the time loop does not compile: {e}");
                            1
                        }
                    }
                }
                Err(e) => {
                    let _ = writeln!(err, "{name}: the kernels do not compile: {e}");
                    1
                }
            }
        }
        Ok((scene, program)) if emit == Emit::Wgsl => {
            use softc_compiler::back::wgsl;
            let p = crate::devices::precision(
                BackendChoice::Gpu,
                precision.map(Into::into),
                program.sim.precision,
            );
            let emitted = match batch {
                Some(n) => wgsl::emit_batched(&scene.adjoint.module, p, n),
                None => wgsl::emit(&scene.adjoint.module, p),
            };
            let checked = emitted.and_then(|m| wgsl::validate(&m.source, p).map(|()| m));
            match checked {
                Ok(m) => {
                    let _ = write!(out, "{}", m.source);
                    0
                }
                Err(e) => {
                    let _ = writeln!(err, "{name}: the kernels do not compile to WGSL: {e}");
                    1
                }
            }
        }
        Ok((scene, _)) => {
            // The forward kernels, then the adjoint of a step.
            let _ = write!(out, "{}", scene.adjoint.module);
            0
        }
        Err(f) => {
            let _ = writeln!(
                err,
                "{name}: cannot compile: {}",
                f.lowering.unwrap_or_default()
            );
            1
        }
    }
}

fn plural(n: usize) -> &'static str {
    if n == 1 { "" } else { "s" }
}

fn report(
    file: &SourceFile,
    diags: &[Diagnostic],
    format: MessageFormat,
    out: &mut dyn Write,
    err: &mut dyn Write,
) {
    for d in diags {
        match format {
            MessageFormat::Human => {
                let _ = writeln!(err, "{}", file.render(d));
            }
            MessageFormat::Json => {
                let _ = writeln!(out, "{}", file.render_json(d));
            }
        }
    }
}

fn fmt_files(files: &[PathBuf], check: bool, out: &mut dyn Write, err: &mut dyn Write) -> i32 {
    let mut status = 0;
    for path in files {
        let Some(bytes) = read_input(path, err) else {
            status = 2;
            continue;
        };
        let name = display_name(path);
        let text = match softc_compiler::decode(&bytes) {
            Ok(t) => t,
            Err(d) => {
                let lossy = String::from_utf8_lossy(&bytes);
                report(
                    &SourceFile::new(&name, &lossy),
                    &[d],
                    MessageFormat::Human,
                    out,
                    err,
                );
                status = status.max(1);
                continue;
            }
        };
        let formatted = match softc_compiler::fmt::format_source(text) {
            Ok(f) => f,
            Err(d) => {
                let file = SourceFile::new(&name, text);
                report(&file, &[d], MessageFormat::Human, out, err);
                let _ = writeln!(err, "{name}: not formatted (fix the syntax error first)");
                status = status.max(1);
                continue;
            }
        };
        if path == Path::new("-") {
            let _ = out.write_all(formatted.as_bytes());
            continue;
        }
        if formatted == text {
            continue;
        }
        if check {
            let _ = writeln!(err, "{name}: not formatted");
            if let Some((line, old, new)) = first_difference(text, &formatted) {
                let _ = writeln!(
                    err,
                    "  first difference at line {line}:\n  - {old}\n  + {new}"
                );
            }
            status = status.max(1);
            continue;
        }
        if let Err(e) = write_atomically(path, formatted.as_bytes()) {
            let _ = writeln!(err, "softc: cannot write `{name}`: {e}");
            status = 2;
        } else {
            let _ = writeln!(err, "{name}: formatted");
        }
    }
    status
}

fn first_difference<'a>(a: &'a str, b: &'a str) -> Option<(usize, &'a str, &'a str)> {
    let mut la = a.lines();
    let mut lb = b.lines();
    let mut n = 0;
    loop {
        n += 1;
        match (la.next(), lb.next()) {
            (None, None) => return None,
            (x, y) if x != y => return Some((n, x.unwrap_or(""), y.unwrap_or(""))),
            _ => {}
        }
    }
}
