//! `voxrad-shard`: the shard conversion tool. Parses arguments and calls `voxrad::convert`, where
//! all the logic lives; maps errors to exit statuses (0 success, 2 bad input, 1 anything else).

use clap::{Parser, Subcommand, ValueEnum};
use std::path::PathBuf;
use voxrad::convert::commands::{self, ConvertOptions};
use voxrad::convert::export::{self, Format};
use voxrad::convert::ConvertError;
use voxrad::outcore::budget::{format_bytes as human, parse_bytes};
use voxrad::voxel::voxelize::GridSpec;

#[derive(Parser)]
#[command(
    name = "voxrad-shard",
    version,
    about = "Make, inspect, verify and re-split voxrad shard sets; export solve results",
    long_about = "Make, inspect, verify and re-split voxrad shard sets; export solve results.\n\n\
        A shard set is a directory holding manifest.json (grid, materials, normals, order, and \
        the list of shards with their record counts and checksums) and shard files of 80-byte \
        surfel records sorted in one lexicographic order, one shard per rank. Every command \
        streams: it holds a bounded amount of memory (--memory) whatever the size of the data.\n\n\
        Exit status: 0 success, 2 bad input (the message names the file), 1 anything else."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// More log output (-v info, -vv debug); RUST_LOG overrides.
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    verbose: u8,
}

#[derive(Subcommand)]
enum Command {
    /// Voxelize an OBJ scene into a shard set, out of core.
    #[command(
        long_about = "Voxelize an OBJ scene (with its MTL) into a shard set, out of core.\n\n\
            The surfels are exactly those `voxrad solve` makes in memory; they are produced in \
            pieces, sorted by an external sort (sorted runs on disk, merged) inside --memory, and \
            written as --ranks shards of equal record counts, contiguous in the set's order. The \
            scene's triangles are held in memory; the surfels never are. The set appears under \
            --out only when complete; an existing shard set there is replaced."
    )]
    Convert {
        /// The scene: an OBJ file (Kd = reflectance, Ke = emitted radiosity).
        scene: PathBuf,
        /// Voxels along the longest side of the scene.
        #[arg(long, required_unless_present = "voxel_size")]
        resolution: Option<u32>,
        /// Voxel edge length in scene units (instead of --resolution).
        #[arg(long, conflicts_with = "resolution")]
        voxel_size: Option<f64>,
        /// The shard set directory to write (new, empty, or a shard set to replace).
        #[arg(long)]
        out: PathBuf,
        /// Number of shards (one per rank).
        #[arg(long, default_value_t = 1)]
        ranks: usize,
        /// Memory budget for the pieces being sorted and the I/O buffers, e.g. 64MiB, 1GiB (at
        /// least 64KiB; the scene's triangles and about 8 MiB of code and stack come on top).
        #[arg(long, default_value = "256MiB", value_parser = parse_bytes)]
        memory: u64,
        /// Lexicographic order of the records (0 to 3: the sign pattern of x and y).
        #[arg(long, default_value_t = 0)]
        order: usize,
        /// Worker threads for sorting (0: all cores; 1: the main thread only).
        #[arg(long, default_value_t = 0)]
        threads: usize,
    },
    /// Print a shard set's manifest: format, grid, bounds, materials, order, shards, totals.
    Inspect {
        /// The shard set directory.
        set: PathBuf,
    },
    /// Check every file of a shard set: magic, version, lengths, checksums, order within and
    /// across shards, and the manifest's counts and checksums against the files.
    Verify {
        /// The shard set directory.
        set: PathBuf,
    },
    /// Re-split a shard set into another number of shards (a streaming merge of the old ones);
    /// the new set is verified to hold the same records before it is moved into place.
    Reshard {
        /// The shard set directory to read.
        set: PathBuf,
        /// Number of shards of the new set.
        #[arg(long)]
        ranks: usize,
        /// The new shard set directory (not the input).
        #[arg(long)]
        out: PathBuf,
        /// Memory budget for the read and write buffers, e.g. 64MiB.
        #[arg(long, default_value = "64MiB", value_parser = parse_bytes)]
        memory: u64,
    },
    /// Stream a solve's per-voxel results (surfels.bin) into a PLY point cloud or a CSV table,
    /// exactly as `voxrad solve` writes them, without holding the records in memory.
    Export {
        /// A directory written by `voxrad solve`, or its surfels.bin.
        results: PathBuf,
        /// Output format.
        #[arg(long, value_enum)]
        format: ExportFormat,
        /// The file to write.
        #[arg(long)]
        out: PathBuf,
    },
}

#[derive(Clone, Copy, ValueEnum)]
enum ExportFormat {
    /// Binary PLY, one coloured vertex per surfel side (as surfels.ply).
    Ply,
    /// x,y,z,nx,ny,nz,B_r,B_g,B_b rows, one per surfel side.
    Csv,
}

fn init_logging(verbose: u8) {
    let default = match verbose {
        0 => "warn,voxrad=info",
        1 => "info",
        _ => "debug",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .init();
}

fn run(cli: Cli) -> Result<(), ConvertError> {
    match cli.command {
        Command::Convert {
            scene,
            resolution,
            voxel_size,
            out,
            ranks,
            memory,
            order,
            threads,
        } => {
            let spec = match (voxel_size, resolution) {
                (Some(v), _) => GridSpec::VoxelSize(v),
                (None, Some(n)) => GridSpec::Resolution(n),
                (None, None) => {
                    return Err(ConvertError::BadInput(
                        "give --resolution or --voxel-size".into(),
                    ))
                }
            };
            let s = commands::convert(&ConvertOptions {
                scene,
                out: out.clone(),
                spec,
                ranks,
                memory,
                order,
                threads,
            })?;
            let bytes: u64 = s.shards.iter().map(|i| i.bytes).sum();
            println!(
                "{} surfels in {} shards ({}) written to {} in {:.1} s; sorted in {} runs of up \
                 to {} pieces under --memory {}",
                s.surfels,
                s.shards.len(),
                human(bytes),
                out.display(),
                s.seconds,
                s.sort.runs,
                s.plan.run_pieces,
                human(s.plan.budget_bytes)
            );
        }
        Command::Inspect { set } => print!("{}", commands::inspect(&set)?),
        Command::Verify { set } => println!("{}", commands::verify(&set)?),
        Command::Reshard {
            set,
            ranks,
            out,
            memory,
        } => {
            let s = commands::reshard(&set, ranks, &out, memory)?;
            println!(
                "{} records re-split into {} shards in {}; verified",
                s.records,
                s.shards.len(),
                out.display()
            );
        }
        Command::Export {
            results,
            format,
            out,
        } => {
            let format = match format {
                ExportFormat::Ply => Format::Ply,
                ExportFormat::Csv => Format::Csv,
            };
            let e = export::export(&results, format, &out)?;
            let what = match format {
                Format::Ply => "vertices",
                Format::Csv => "rows",
            };
            println!(
                "{} {what} written to {} ({} passes over the input)",
                e.items,
                out.display(),
                e.passes
            );
        }
    }
    Ok(())
}

fn main() {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let _ = e.print();
            std::process::exit(code);
        }
    };
    init_logging(cli.verbose);
    if let Err(e) = run(cli) {
        eprintln!("error: {e}");
        std::process::exit(e.exit_code());
    }
}
