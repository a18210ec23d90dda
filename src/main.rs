//! The `voxrad` command line: parses arguments and dispatches to `voxrad::app`; maps errors to
//! exit statuses (0 success, 2 bad input, 3 solve interrupted by a signal with a checkpoint to
//! resume from, 1 anything else).

use clap::{Parser, Subcommand};
use std::path::PathBuf;
use voxrad::app::{
    run_bake, run_generate, run_grid, run_probe, run_render, run_solve, run_study, AppError,
    CheckpointOptions, GenerateScene, SolveCommand,
};
use voxrad::distribute::Mode;
use voxrad::output::report::Report;
use voxrad::quality::Quality;
use voxrad::solve::direct::DirectPass;
use voxrad::solve::SolveOptions;
use voxrad::voxel::voxelize::GridSpec;

#[derive(Parser)]
#[command(
    name = "voxrad",
    version,
    about = "Discrete voxel radiosity for very large scenes",
    after_help = EXIT_STATUS
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// More log output (-v info, -vv debug); RUST_LOG overrides.
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    verbose: u8,
}

const EXIT_STATUS: &str = "Exit status: 0 success; 2 bad input (the message names the file); \
3 a solve stopped by SIGTERM or SIGINT after writing a checkpoint (rerun the same command with \
--resume); 1 anything else.";

#[derive(Subcommand)]
enum Command {
    /// Solve the radiosity of a scene (an .obj file with its .mtl) and write the results.
    ///
    /// Checkpoints: the solve saves its state in OUT/checkpoint.bin at iteration boundaries and
    /// inside long iterations between directions (at most every --checkpoint-every seconds), and
    /// on SIGTERM or SIGINT, which stop it with exit status 3; `--resume` continues from the
    /// checkpoint with the same result an uninterrupted run gives. A finished solve removes its
    /// checkpoint.
    // Negative numbers are values, so `--tolerance -1` reaches the validation that names the
    // option instead of failing as an "unexpected argument '-1'".
    #[command(allow_negative_numbers = true, after_help = EXIT_STATUS)]
    Solve {
        /// The scene: an OBJ file (Kd = reflectance, Ke = emitted radiosity), or a shard-set
        /// directory made by `voxrad-shard convert` (solved out of core).
        scene: PathBuf,
        /// Output directory: report.json, surfels.bin, surfels.ply, render.png.
        #[arg(long)]
        out: PathBuf,
        /// Quality preset: resolution, directions, tolerance and extrapolation (tail and
        /// Chebyshev) chosen together from the accuracy/time study (see docs/study.md);
        /// explicit options override it.
        #[arg(long, value_enum, default_value = "default")]
        quality: QualityArg,
        /// Voxels along the longest side of the scene (default: from --quality).
        #[arg(long, conflicts_with = "voxel_size")]
        resolution: Option<u32>,
        /// Voxel edge length in scene units (instead of --resolution).
        #[arg(long)]
        voxel_size: Option<f64>,
        /// Approximate number of line directions, each covering s and -s (default: from
        /// --quality).
        #[arg(long)]
        directions: Option<usize>,
        /// Dense line directions for the direct light of small emitters, gathered once from the
        /// lines through the emitters only; the bounces use --directions (0: no direct pass;
        /// default: from --quality, used where at most 5 % of the surfels emit). Given
        /// explicitly, the pass runs whatever the emitters' size.
        #[arg(long)]
        direct_directions: Option<usize>,
        /// Largest number of iterations; given without --tolerance, exactly this many are run.
        #[arg(long)]
        iterations: Option<usize>,
        /// Stop when the estimated relative error left falls below this.
        #[arg(long)]
        tolerance: Option<f64>,
        /// Worker threads (default: all cores).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Preview image size, WIDTHxHEIGHT.
        #[arg(long, default_value = "800x600", value_parser = parse_size)]
        image_size: (u32, u32),
        /// Solve out of core, holding at most this much (e.g. 512MiB, 4G; per rank with
        /// `--distribute data|hybrid`); a shard set is always solved out of core (default: a
        /// quarter of the available memory).
        #[arg(long, value_parser = voxrad::outcore::parse_bytes)]
        memory: Option<u64>,
        /// In memory: keep each direction's partner links between iterations within this many
        /// bytes per rank, so that iterations after the first only stream the light along them
        /// (0: find them again in every iteration; default: 4 GiB, at most a quarter of the
        /// memory available once the scene is loaded, the node's or a batch job's limit's,
        /// shared by the ranks on one node).
        #[arg(long, value_parser = voxrad::outcore::parse_bytes_or_zero)]
        links_memory: Option<u64>,
        /// Out of core: keep each direction's partner links in work files taking at most this
        /// much disk (per rank), so that iterations after the first read the light and the
        /// links instead of searching again (0: search in every iteration; default: half of the
        /// disk left free once the work files are made, shared by the ranks on one node, with
        /// room left for two checkpoints where they share that disk).
        #[arg(long, value_parser = voxrad::outcore::parse_bytes_or_zero)]
        links_disk: Option<u64>,
        /// Out of core: make the work files (read and written in every iteration) and an OBJ
        /// scene's temporary shard set under this directory instead of under --out, for example
        /// on a node-local disk while --out is on a shared file system. Each --out gets its own
        /// subdirectory there; checkpoints stay in --out (default: --out).
        #[arg(long, value_name = "DIR")]
        work_dir: Option<PathBuf>,
        /// Under mpirun: how to share the solve between ranks (`directions`: every rank holds
        /// the scene and takes a share of the directions; `data`: ranks own whole lines and
        /// surfels move between them; `hybrid`: groups of ranks share the directions, the data
        /// is distributed inside a group). Needs a build with `--features mpi`.
        #[arg(long, value_enum)]
        distribute: Option<Distribute>,
        /// With `--distribute hybrid`: number of direction groups, a divisor of the rank count
        /// (default: the largest divisor not above its square root).
        #[arg(long, requires = "distribute")]
        groups: Option<usize>,
        /// With `--distribute data|hybrid`: compress the surfels sent between ranks with zstd
        /// (several times smaller, a few ns per byte: worth it on a slow network only).
        #[arg(long, requires = "distribute")]
        compress_exchange: bool,
        /// Where the tail extrapolation finds no geometric tail (scenes of many rooms), iterate
        /// by Chebyshev semi-iteration, which follows several slow modes at once: about a
        /// third fewer iterations on such scenes (docs/simulation.md). On in every --quality
        /// preset; under the stopping rule only, as the tail extrapolation: `--iterations K`
        /// alone runs K plain iterations.
        #[arg(long, overrides_with = "no_chebyshev")]
        chebyshev: bool,
        /// Iterate with the tail extrapolation alone (the solver before the Chebyshev
        /// semi-iteration: its answers to the bit).
        #[arg(long, overrides_with = "chebyshev")]
        no_chebyshev: bool,
        /// Continue from OUT/checkpoint.bin if there is one (left by an interrupted or killed
        /// solve of the same scene and options), at the iteration or the direction it holds;
        /// without one, start from the beginning. A checkpoint written inside an iteration by
        /// another rank count, another --distribute mode or another --groups restarts that
        /// iteration.
        #[arg(long)]
        resume: bool,
        /// Least seconds between two checkpoints, written after an iteration or, inside one,
        /// between directions. 0: after every iteration, and inside iterations as often as
        /// their writing time allows (at most a fifth of the time). A stop signal always saves
        /// what is done. [default: 60, and inside iterations at most a twentieth of the time]
        #[arg(long, value_name = "SECONDS")]
        checkpoint_every: Option<f64>,
    },
    /// Render a solved result directory to a PNG.
    Render {
        /// A directory written by `voxrad solve`.
        dir: PathBuf,
        /// The PNG to write.
        #[arg(long)]
        out: PathBuf,
        /// Camera: eye=X,Y,Z;target=X,Y,Z[;up=X,Y,Z][;fov=DEGREES] (default: automatic framing).
        #[arg(long)]
        camera: Option<String>,
        /// Image size, WIDTHxHEIGHT.
        #[arg(long, default_value = "800x600", value_parser = parse_size)]
        size: (u32, u32),
    },
    /// Irradiance on a workplane: sensors on a horizontal grid gather the solved light; writes
    /// PREFIX.csv and PREFIX.png (false colour, with min, mean, max and uniformity).
    Grid {
        /// A directory written by `voxrad solve`.
        dir: PathBuf,
        /// The plane's height along the up axis (scene units), e.g. 0.8 above a floor at 0.
        #[arg(long, allow_hyphen_values = true)]
        height: f64,
        /// Distance between sensors (scene units).
        #[arg(long)]
        spacing: f64,
        /// Output prefix: writes PREFIX.csv and PREFIX.png.
        #[arg(long)]
        out: PathBuf,
        /// The up axis, which the sensors face.
        #[arg(long, value_enum, default_value = "y")]
        up: Axis,
        /// The plane's extent along the first other axis (x, or y when up is x), LOW,HIGH
        /// (default: the scene's).
        #[arg(long, value_parser = parse_range, allow_hyphen_values = true)]
        first: Option<[f64; 2]>,
        /// The plane's extent along the second other axis (z, or y when up is z), LOW,HIGH
        /// (default: the scene's).
        #[arg(long, value_parser = parse_range, allow_hyphen_values = true)]
        second: Option<[f64; 2]>,
        /// Line directions each sensor gathers the reflected light along (emitters are summed
        /// one by one besides). A grid has many sensors, so the default stays at 2,000 whatever
        /// the resolution (`probe --gather` takes more at high resolutions).
        #[arg(long, default_value_t = 2000)]
        directions: usize,
    },
    /// Bake a solve's radiosity onto its scene's triangles: glTF binary (.glb) or PLY mesh (.ply).
    Bake {
        /// A directory written by `voxrad solve`.
        dir: PathBuf,
        /// The OBJ scene (default: the scene `DIR/report.json` names).
        #[arg(long)]
        scene: Option<PathBuf>,
        /// The file to write: FILE.glb or FILE.ply.
        #[arg(long)]
        out: PathBuf,
    },
    /// Write a generated scene (OBJ + MTL) for tests, examples and scale runs.
    Generate {
        /// Which scene.
        #[arg(value_enum)]
        scene: SceneKind,
        /// The OBJ file to write (its MTL is written beside it).
        #[arg(long)]
        out: PathBuf,
        /// For `building`: rooms along x, along z, and floors, as XxZxF.
        #[arg(long, default_value = "2x2x1", value_parser = parse_triple)]
        rooms: (usize, usize, usize),
        /// For `room`: pieces of furniture.
        #[arg(long, default_value_t = 4)]
        furniture: usize,
        /// Seed of the generator (same seed, same scene).
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// For `thin-slab`: the slab's thickness in voxels at resolution 128 (voxel 1/127 m).
        #[arg(long, default_value_t = 1.0)]
        thickness: f64,
        /// For `thin-slab`: rotation in degrees about y and about x, as Y,X (0,0: axis-aligned).
        #[arg(long, default_value = "0,0", value_parser = parse_pair)]
        tilt: (f64, f64),
        /// For `thin-slab`: `side` (a panel in a side wall) or `top` (a ceiling strip beside
        /// the slab, grazing light).
        #[arg(long, value_enum, default_value = "side")]
        light: LightKind,
        /// For `hard-twin`: which twin of a furnace hard case.
        #[arg(long, value_enum, default_value = "white-box")]
        twin: TwinKind,
        /// Also write the scene's probe points (x,y,z,nx,ny,nz) to this CSV file: the
        /// generator's own for office, window-room, corridor, thin-slab and hard-twin, else 300
        /// points drawn like `voxrad study`'s (seed 0x5eed).
        #[arg(long)]
        probes: Option<PathBuf>,
        /// Also write each probe's surface label (probe,surface) to this CSV file.
        #[arg(long)]
        surfaces: Option<PathBuf>,
    },
    /// What accuracy costs in time: sweeps directions, tolerance and resolution, measures each
    /// run's error and time; writes study.csv, study.md and study.png.
    Study {
        /// A built-in scene (`furnace`, `cornell`), an OBJ file, or a directory of path-traced
        /// reference data (`scene.obj` and `reference.csv`, as in tests/data/reference/NAME),
        /// whose probes then measure the error.
        scene: String,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// A small, fast sweep (for tests and a first look).
        #[arg(long)]
        quick: bool,
        /// Only the quality presets, no sweep.
        #[arg(long, conflicts_with = "quick")]
        presets: bool,
        /// Worker threads (default: all cores).
        #[arg(long, default_value_t = 0)]
        threads: usize,
    },
    /// Radiosity and irradiance at given surface points: reads x,y,z,nx,ny,nz rows, prints a
    /// header and x,y,z,nx,ny,nz,B_r,B_g,B_b,H_r,H_g,H_b rows.
    Probe {
        /// A directory written by `voxrad solve`.
        dir: PathBuf,
        /// CSV file of points and normals.
        #[arg(long)]
        points: PathBuf,
        /// Write the rows to this CSV file instead of standard output.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Gather the light at each point (sensors as `voxrad grid`'s, along this many line
        /// directions, and every emitter) instead of reading the surfels near it: slower,
        /// several times closer to a path-traced answer (docs/formats.md). Without a count:
        /// 2,000 at resolution 64, growing with the square of the resolution up to 32,000.
        #[arg(long, num_args = 0..=1, value_name = "DIRECTIONS")]
        gather: Option<Option<usize>>,
    },
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum Distribute {
    /// Directions dealt out to ranks; every rank holds the whole scene.
    Directions,
    /// Whole lines owned by ranks; surfels move to their line's rank per direction.
    Data,
    /// Groups of ranks share the directions; inside a group the data is distributed.
    Hybrid,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum QualityArg {
    /// A first look in seconds (resolution 32, 109 directions, tolerance 1e-2).
    Draft,
    /// Balanced (resolution 64, 301 directions, tolerance 1e-4).
    Default,
    /// Slow and accurate (resolution 256, 433 directions, tolerance 1e-4).
    High,
}

/// An axis of the scene.
#[derive(Clone, Copy, clap::ValueEnum)]
enum Axis {
    X = 0,
    Y = 1,
    Z = 2,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SceneKind {
    /// The Cornell box (the same as examples/cornell_box.obj).
    Cornell,
    /// One closed, lit, furnished room.
    Room,
    /// A building of many rooms with thick walls and doors (size knob: --rooms).
    Building,
    /// A lit room beside a sealed dark one.
    SealedRooms,
    /// A closed glowing cube with exact answer B = E / (1 - rho) (E = 1, rho = 0.5).
    Furnace,
    /// Two facing unit squares 1 apart: emitter E = 1, receiver rho = 0.5 (analytic form factor).
    ParallelSquares,
    /// A 12 x 3 x 8 m open-plan office with 12 suspended luminaires, desks, partitions, cabinets.
    Office,
    /// A furnished 5 x 2.8 x 4 m room lit by a 2 x 1.4 m window-sized emitter.
    WindowRoom,
    /// A corridor with six rooms opening onto it through doors, lit by small lamps.
    Corridor,
    /// A closed 1 m box with a thin slab in the middle (--thickness, --tilt, --light).
    ThinSlab,
    /// A furnace hard case's geometry lit by one lamp (--twin).
    HardTwin,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum TwinKind {
    /// Walls of reflectance 0.999, a small lamp in the ceiling.
    WhiteBox,
    /// The same box with every reflectance 0.
    BlackBox,
    /// A slab 0.01 thick and a cube on voxel corners (resolution 25), lit from the wall x = 0.
    Slab,
    /// The same with the slab tilted by 0.05 rad.
    SlabTilted,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum LightKind {
    Side,
    Top,
}

fn parse_pair(text: &str) -> Result<(f64, f64), String> {
    let parts: Vec<Option<f64>> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect();
    match parts[..] {
        [Some(a), Some(b)] => Ok((a, b)),
        _ => Err(format!("'{text}' is not two numbers Y,X")),
    }
}

/// A distributed solve under MPI (a build with the `mpi` feature): the report and this rank.
#[cfg(feature = "mpi")]
fn solve_under_mpi(cmd: &SolveCommand, mode: Mode) -> Result<(Report, usize), AppError> {
    use voxrad::distribute::{mpi_comm::MpiComm, Comm};
    let comm = MpiComm::init()
        .ok_or_else(|| AppError::Failure("MPI could not be initialized".to_string()))?;
    // Again after MPI's start-up, which may have set handlers of its own.
    if let Err(e) = voxrad::interrupt::install() {
        tracing::warn!("cannot handle SIGTERM and SIGINT ({e})");
    }
    let outcome = voxrad::app::run_solve_on(cmd, &comm, mode);
    if let Err(e) = &outcome {
        end_if_alone(e);
    }
    let rank = comm.rank();
    // MPI's end (`MPI_Finalize`) when `comm` drops.
    drop(comm);
    Ok((outcome?, rank))
}

/// How long a rank that failed waits for MPI's end before it gives up on it.
#[cfg(feature = "mpi")]
const FINALIZE_GRACE: std::time::Duration = std::time::Duration::from_secs(20);

/// A rank that failed alone (its own file, its own disk) would wait for ever in MPI's end while
/// the others wait for it in their next collective call. So a watchdog: if MPI's end has not
/// come after [`FINALIZE_GRACE`], this rank says why and exits without it, and the launcher
/// ends the whole job. When every rank failed together (the errors they agree on), MPI's end
/// comes at once and the error is reported as usual.
#[cfg(feature = "mpi")]
fn end_if_alone(error: &AppError) {
    let (message, code) = (error.to_string(), error.exit_code());
    std::thread::spawn(move || {
        std::thread::sleep(FINALIZE_GRACE);
        eprintln!("error: {message}");
        eprintln!(
            "error: the other ranks did not stop with this one; ending without MPI's end, so \
             that the launcher stops the job"
        );
        // Not `process::exit`: MPI's exit handlers could wait for the other ranks again.
        // SAFETY: `_exit` ends the process at once; nothing of it is used afterwards.
        unsafe { libc::_exit(code) }
    });
}

#[cfg(not(feature = "mpi"))]
fn solve_under_mpi(_cmd: &SolveCommand, _mode: Mode) -> Result<(Report, usize), AppError> {
    Err(AppError::BadInput(
        "--distribute needs MPI: this voxrad was built without it; build with `cargo build \
         --release --features mpi` (needs an MPI library such as libopenmpi-dev, and libclang)"
            .to_string(),
    ))
}

fn parse_triple(text: &str) -> Result<(usize, usize, usize), String> {
    let parts: Vec<Option<usize>> = text
        .split('x')
        .map(|p| p.trim().parse::<usize>().ok().filter(|&v| v > 0))
        .collect();
    match parts[..] {
        [Some(a), Some(b), Some(c)] => Ok((a, b, c)),
        _ => Err(format!(
            "'{text}' is not XxZxF with whole numbers of at least 1"
        )),
    }
}

fn parse_range(text: &str) -> Result<[f64; 2], String> {
    let (a, b) = text
        .split_once(',')
        .ok_or_else(|| format!("'{text}' is not LOW,HIGH"))?;
    let parse = |s: &str| s.trim().parse::<f64>().ok().filter(|v| v.is_finite());
    match (parse(a), parse(b)) {
        (Some(a), Some(b)) if b > a => Ok([a, b]),
        _ => Err(format!("'{text}' is not LOW,HIGH with LOW < HIGH")),
    }
}

fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text
        .split_once('x')
        .ok_or_else(|| format!("'{text}' is not WIDTHxHEIGHT"))?;
    let parse = |s: &str| {
        s.trim()
            .parse::<u32>()
            .ok()
            .filter(|&v| v > 0 && v <= 16384)
    };
    match (parse(w), parse(h)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => Err(format!(
            "'{text}': width and height must be whole numbers from 1 to 16384"
        )),
    }
}

/// Largest `--direct-directions`: far past any measured gain (`docs/simulation.md`),
/// and a typo of a few digits more would otherwise run for hours.
const MAX_DIRECT_DIRECTIONS: usize = 1_000_000;

fn run(cli: Cli) -> Result<(), AppError> {
    match cli.command {
        Command::Solve {
            scene,
            out,
            quality,
            resolution,
            voxel_size,
            directions,
            direct_directions,
            iterations,
            tolerance,
            threads,
            image_size,
            memory,
            links_memory,
            links_disk,
            work_dir,
            distribute,
            groups,
            compress_exchange,
            chebyshev,
            no_chebyshev,
            resume,
            checkpoint_every,
        } => {
            let (seconds, write_factor) = match checkpoint_every {
                Some(s) => (s, voxrad::checkpoint::ASKED_WRITE_TIME_FACTOR),
                None => (60.0, voxrad::checkpoint::WRITE_TIME_FACTOR),
            };
            let every = std::time::Duration::try_from_secs_f64(seconds).map_err(|_| {
                AppError::BadInput(format!(
                    "--checkpoint-every {seconds}: must be a number of seconds, 0 or more"
                ))
            })?;
            if memory.is_some() || scene.is_dir() {
                // Before any thread starts (see the function).
                voxrad::outcore::solver::one_malloc_arena();
            }
            // From here SIGTERM and SIGINT stop the solve at the next direction, with a
            // checkpoint, instead of killing the process.
            if let Err(e) = voxrad::interrupt::install() {
                tracing::warn!("cannot handle SIGTERM and SIGINT ({e}); they will end the solve without a checkpoint");
            }
            voxrad::interrupt::watch_setup(format!(
                "nothing new to save: rerun with --resume (it continues from {} if there is one)",
                voxrad::checkpoint::path_in(&out).display()
            ));
            let preset = match quality {
                QualityArg::Draft => Quality::Draft,
                QualityArg::Default => Quality::Default,
                QualityArg::High => Quality::High,
            }
            .preset();
            let directions = directions.unwrap_or(preset.directions);
            let grid = match voxel_size {
                Some(v) => GridSpec::VoxelSize(v),
                None => GridSpec::Resolution(resolution.unwrap_or(preset.resolution)),
            };
            if let Some(t) = tolerance {
                if !(t.is_finite() && t > 0.0) {
                    return Err(AppError::BadInput(format!(
                        "--tolerance {t}: must be a positive number"
                    )));
                }
            }
            if direct_directions.is_some_and(|n| n > MAX_DIRECT_DIRECTIONS) {
                return Err(AppError::BadInput(format!(
                    "--direct-directions {}: at most {MAX_DIRECT_DIRECTIONS} (80,000 already \
                     leaves the directions' error below the voxels')",
                    direct_directions.unwrap_or(0)
                )));
            }
            if directions == 0 {
                return Err(AppError::BadInput(
                    "--directions 0: at least one direction is needed".into(),
                ));
            }
            let defaults = SolveOptions::default();
            let solve = SolveOptions {
                directions,
                max_iterations: iterations.unwrap_or(defaults.max_iterations),
                tolerance: match (tolerance, iterations) {
                    (Some(t), _) => Some(t),
                    (None, Some(_)) => None,
                    (None, None) => Some(preset.tolerance),
                },
                threads,
                // Extrapolation only under the tolerance rule: `--iterations K` alone asks for K
                // plain Jacobi sweeps.
                accelerate: preset.accelerate && (tolerance.is_some() || iterations.is_none()),
                direct: match direct_directions {
                    None => DirectPass::Auto(preset.direct),
                    Some(0) => DirectPass::Off,
                    Some(n) => DirectPass::On(n),
                },
                links_memory,
                links_disk,
                chebyshev: (preset.chebyshev || chebyshev)
                    && !no_chebyshev
                    && preset.accelerate
                    && (tolerance.is_some() || iterations.is_none()),
                ..Default::default()
            };
            let cmd = SolveCommand {
                scene,
                out: out.clone(),
                grid,
                solve,
                image_size,
                memory,
                checkpoint: CheckpointOptions {
                    resume,
                    every,
                    write_factor,
                },
                work_dir,
            };
            if groups.is_some() && !matches!(distribute, Some(Distribute::Hybrid)) {
                return Err(AppError::BadInput(
                    "--groups applies to --distribute hybrid only".into(),
                ));
            }
            if groups == Some(0) {
                return Err(AppError::BadInput(
                    "--groups 0: at least one group is needed".into(),
                ));
            }
            let (report, rank) = match distribute {
                None => (run_solve(&cmd)?, 0),
                Some(Distribute::Directions) => solve_under_mpi(&cmd, Mode::Directions)?,
                Some(Distribute::Data) => solve_under_mpi(
                    &cmd,
                    Mode::Data {
                        compress: compress_exchange,
                    },
                )?,
                Some(Distribute::Hybrid) => solve_under_mpi(
                    &cmd,
                    Mode::Hybrid {
                        groups: groups.unwrap_or(0),
                        compress: compress_exchange,
                    },
                )?,
            };
            if rank != 0 {
                // Only rank 0 speaks for the run.
                return Ok(());
            }
            eprintln!(
                "{} voxels, {} directions, {} iterations ({}), {:.1} s; results in {}",
                report.voxels,
                report.directions,
                report.iterations,
                if report.converged {
                    "converged"
                } else {
                    "not converged"
                },
                report.seconds.get("total").copied().unwrap_or(0.0),
                out.display()
            );
            Ok(())
        }
        Command::Render {
            dir,
            out,
            camera,
            size,
        } => run_render(&dir, &out, camera.as_deref(), size),
        Command::Probe {
            dir,
            points,
            out,
            gather,
        } => run_probe(&dir, &points, out.as_deref(), gather),
        Command::Bake { dir, scene, out } => run_bake(&dir, scene.as_deref(), &out),
        Command::Grid {
            dir,
            height,
            spacing,
            out,
            up,
            first,
            second,
            directions,
        } => {
            let extent = [first, second];
            let spec = voxrad::output::grid::GridSpec {
                up: up as usize,
                height,
                spacing,
                extent,
            };
            run_grid(&dir, &spec, directions, &out)
        }
        Command::Study {
            scene,
            out,
            quick,
            presets,
            threads,
        } => {
            let study = run_study(&scene, &out, quick, presets, threads)?;
            eprintln!(
                "{} runs; reference: {}; study.csv, study.md, study.png in {}",
                study.runs.len(),
                study.reference,
                out.display()
            );
            Ok(())
        }
        Command::Generate {
            scene,
            out,
            rooms,
            furniture,
            seed,
            thickness,
            tilt,
            light,
            twin,
            probes,
            surfaces,
        } => {
            let scene = match scene {
                SceneKind::Cornell => GenerateScene::Cornell,
                SceneKind::Room => GenerateScene::Room { furniture, seed },
                SceneKind::Building => GenerateScene::Building { rooms, seed },
                SceneKind::SealedRooms => GenerateScene::SealedRooms,
                SceneKind::Furnace => GenerateScene::Furnace,
                SceneKind::ParallelSquares => GenerateScene::ParallelSquares,
                SceneKind::Office => GenerateScene::Office,
                SceneKind::WindowRoom => GenerateScene::WindowRoom,
                SceneKind::Corridor => GenerateScene::Corridor,
                SceneKind::HardTwin => GenerateScene::HardTwin(match twin {
                    TwinKind::WhiteBox => voxrad::gen::HardTwin::WhiteBox,
                    TwinKind::BlackBox => voxrad::gen::HardTwin::BlackBox,
                    TwinKind::Slab => voxrad::gen::HardTwin::Slab,
                    TwinKind::SlabTilted => voxrad::gen::HardTwin::SlabTilted,
                }),
                SceneKind::ThinSlab => {
                    if !(thickness.is_finite() && thickness > 0.0) {
                        return Err(AppError::BadInput(format!(
                            "--thickness {thickness}: the slab needs a positive thickness"
                        )));
                    }
                    GenerateScene::ThinSlab {
                        thickness,
                        tilt: [tilt.0, tilt.1],
                        light: match light {
                            LightKind::Side => voxrad::gen::SlabLight::Side,
                            LightKind::Top => voxrad::gen::SlabLight::Top,
                        },
                    }
                }
            };
            let triangles = run_generate(scene, &out, probes.as_deref(), surfaces.as_deref())?;
            eprintln!("{triangles} triangles written to {}", out.display());
            Ok(())
        }
    }
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
    voxrad::progress::init_logging(cli.verbose);
    if let Err(e) = run(cli) {
        eprintln!("error: {e}");
        std::process::exit(e.exit_code());
    }
}
