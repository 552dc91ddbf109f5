//! `softc mesh ...`: generate, inspect, convert meshes, and build the benchmark grid.

use std::io::Write;
use std::path::PathBuf;

use crate::mesh::{LengthUnit, commands};

/// Mesh subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum MeshCommand {
    /// Mesh a TOML spec (primitives or closed STL surfaces; see meshes/README.md) into tets.
    Generate {
        /// The spec file (.toml).
        spec: PathBuf,
        /// Output mesh (.msh gmsh 4.1 or .vtu), written atomically.
        #[arg(short, long)]
        output: PathBuf,
        /// Lattice spacing in the spec's length unit, overriding the spec's `resolution`.
        #[arg(short, long)]
        resolution: Option<f64>,
    },
    /// Print counts, tags, chamber volumes, quality and validation; exit 1 if invalid.
    Info {
        file: PathBuf,
        /// Machine-readable output (SI units).
        #[arg(long)]
        json: bool,
        /// Length unit of the file's coordinates.
        #[arg(long, default_value = "mm")]
        unit: String,
    },
    /// Convert any readable mesh (.msh .vtk .vtu .node/.ele .inp) to .msh or .vtu, optionally
    /// to the other element order (--order 1 or 2).
    Convert {
        input: PathBuf,
        output: PathBuf,
        /// Length unit of the files' coordinates.
        #[arg(long, default_value = "mm")]
        unit: String,
        /// Renumber the nodes so that each element's nodes are numbered close together (reverse
        /// Cuthill–McKee): kernels run up to a third faster on a mesh whose mesher scattered
        /// them (`softc mesh info` shows the node span).
        #[arg(long)]
        renumber: bool,
        /// Element order of the output: 2 inserts a straight-sided mid-edge node on every
        /// edge (10-node tets, 6-node tagged triangles; node sets gain the nodes on their
        /// edges), 1 drops the mid-edge nodes. Default: the input's order.
        #[arg(long, value_parser = clap::value_parser!(u8).range(1..=2))]
        order: Option<u8>,
    },
    /// How converged a static script's answer is: its static solve at each element order and
    /// mesh resolution asked for (other resolutions regenerated from the `.toml` spec beside
    /// the mesh), then how far the script's own answer (resolution 1, the first order) is
    /// from the converged reference (Richardson extrapolation over three or more resolutions,
    /// else the finest answer of the first order), how much each order moves between its
    /// two finest meshes and how far the orders are apart. The table is `bench --tradeoff`'s.
    Converge {
        /// A script with a static solve (`integrator = quasi_static`) of a loaded mesh.
        script: PathBuf,
        /// Element orders; the first is the reference's and the script's own answer's.
        #[arg(long, default_value = "2,1")]
        orders: String,
        /// Mesh refinement factors (1 = the script's own mesh; others need the spec).
        #[arg(long, default_value = "1")]
        resolutions: String,
        /// The quantity: `loss` (the script's loss), or SET.AXIS (a node set's mean
        /// displacement).
        #[arg(long, default_value = "loss")]
        output: String,
        /// A param or input value, with its unit (`--set p=20kPa`).
        #[arg(long)]
        set: Vec<String>,
        /// Threads of the cpu backend.
        #[arg(long)]
        threads: Option<usize>,
        /// Folder of the table's JSON, plots, meshes and variant scripts.
        #[arg(long, default_value = "converge")]
        out: PathBuf,
    },
    /// The structured Kuhn-split benchmark scene (BENCHMARK.md), e.g. 12 4 4 for "1k".
    Kuhn {
        nx: usize,
        ny: usize,
        nz: usize,
        #[arg(short, long)]
        output: PathBuf,
        /// Element order: 2 writes 10-node tets (a straight-sided mid-edge node on every edge;
        /// the grid's faces are planes, so nothing is lost to curvature).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2))]
        order: u8,
    },
}

fn unit(s: &str, err: &mut dyn Write) -> Result<LengthUnit, i32> {
    s.parse::<LengthUnit>().map_err(|e| {
        let _ = writeln!(err, "error: --unit {s}: {e}");
        2
    })
}

/// Run a mesh subcommand: 0 ok, 1 bad input (message on `err` naming file and problem),
/// 2 usage.
pub fn run(cmd: MeshCommand, out: &mut dyn Write, err: &mut dyn Write) -> i32 {
    match cmd {
        MeshCommand::Generate {
            spec,
            output,
            resolution,
        } => {
            if let Some(r) = resolution.filter(|r| !(*r > 0.0 && r.is_finite())) {
                let _ = writeln!(err, "error: --resolution {r}: must be a positive number");
                return 2;
            }
            commands::generate(&spec, &output, resolution, out, err)
        }
        MeshCommand::Info {
            file,
            json,
            unit: u,
        } => match unit(&u, err) {
            Ok(u) => commands::info(&file, u, json, out, err),
            Err(c) => c,
        },
        MeshCommand::Convert {
            input,
            output,
            unit: u,
            renumber,
            order,
        } => match unit(&u, err) {
            Ok(u) => commands::convert(&input, &output, u, renumber, order, out, err),
            Err(c) => c,
        },
        MeshCommand::Kuhn {
            nx,
            ny,
            nz,
            output,
            order,
        } => commands::kuhn([nx, ny, nz], order, &output, out, err),
        // `bench --tradeoff` restricted to static solves: `cli/mod.rs` runs it through
        // `cli::bench` before it gets here.
        MeshCommand::Converge { .. } => {
            let _ = writeln!(
                err,
                "error: `mesh converge` is run by the command line's root"
            );
            2
        }
    }
}
