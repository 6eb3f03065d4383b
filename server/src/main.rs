use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use voxstream::pipeline::progress::Progress;
use voxstream::pipeline::voxelize::Topology;
use voxstream::pipeline::{BuildOptions, Resolution, build_scene_reporting, parse_byte_size};

/// voxstream: huge 3D scans as streamed voxel blocks.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Voxelize a mesh (OBJ, PLY, STL, glTF/GLB) into LOD blocks and publish it to a store.
    Build {
        /// The mesh file.
        mesh: PathBuf,
        /// The store directory; the scene is published as <out>/<name>.
        #[arg(long)]
        out: PathBuf,
        /// Level-0 voxels per edge of the mesh's bounding cube: `auto` (the power of
        /// two whose voxel is closest to the scan's median triangle edge) or a power of two.
        #[arg(long, default_value = "auto", conflicts_with = "voxel_size")]
        resolution: Resolution,
        /// Voxel edge in source units, instead of --resolution: the grid is the next
        /// power of two that covers the mesh.
        #[arg(long)]
        voxel_size: Option<f64>,
        /// Scene id (a-z, 0-9, '-', '_'); defaults to the file name.
        #[arg(long)]
        name: Option<String>,
        /// Which voxels a triangle sets: every voxel it touches, or the thinner
        /// sets that still block 26- or 6-connected paths through a closed surface.
        #[arg(long, value_enum, default_value_t = TopologyArg::Conservative)]
        topology: TopologyArg,
        /// Memory the build may hold (bytes, or with a K/M/G suffix: 1GiB, 512M); the rest goes to temp files.
        #[arg(long, default_value = "1GiB", value_parser = parse_byte_size)]
        memory_budget: u64,
        /// Directory for the build's temporary files (default: inside --out); removed afterwards.
        #[arg(long)]
        tmp: Option<PathBuf>,
    },
    /// Write a synthetic scan (a displaced, finely tessellated sphere) as binary PLY.
    Synth {
        /// At least this many triangles (rounded up to a whole tessellation).
        #[arg(long)]
        triangles: u64,
        #[arg(long)]
        out: PathBuf,
    },
    /// Measure build throughput, peak memory and size against meshoptimizer's
    /// cluster-LOD build; prints JSON (see DEVELOPERS.md, "Benchmarks").
    Bench(voxstream::bench::BenchArgs),
    /// One meshoptimizer peer run for `bench`, as JSON.
    #[command(hide = true)]
    BenchMeshopt(voxstream::bench::BenchMeshoptArgs),
    /// Serve a store's scenes and the viewer over HTTP; take uploads and build them.
    Serve(voxstream::config::ServeArgs),
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum TopologyArg {
    Conservative,
    #[value(name = "26-separating")]
    Separating26,
    #[value(name = "6-separating")]
    Separating6,
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,tower_http=info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("voxstream: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Build { mesh, out, resolution, voxel_size, name, topology, memory_budget, tmp } => {
            let resolution = voxel_size.map_or(resolution, Resolution::VoxelSize);
            let topology = match topology {
                TopologyArg::Conservative => Topology::Conservative,
                TopologyArg::Separating26 => Topology::Separating26,
                TopologyArg::Separating6 => Topology::Separating6,
            };
            // indicatif draws only on a terminal, so scripts and CI logs stay clean.
            let bar = indicatif::ProgressBar::new(1000).with_style(
                indicatif::ProgressStyle::with_template(
                    "{spinner} {msg:28} [{bar:32}] {percent:>3}% eta {eta}",
                )
                .expect("static template")
                .progress_chars("=> "),
            );
            let report = |p: Progress| {
                bar.set_position((p.fraction * 1000.0) as u64);
                bar.set_message(format!("{} {:.2} Mtri/s", p.stage.name(), p.triangles_per_second / 1e6));
            };
            let result = build_scene_reporting(
                &mesh,
                &out,
                &BuildOptions {
                    resolution,
                    name,
                    topology,
                    cancel: None,
                    memory_budget,
                    temp_dir: tmp,
                    ..Default::default()
                },
                &report,
            );
            bar.finish_and_clear();
            let r = result?;
            println!(
                "built scene {:?} in {:.2} s: {} triangles ({} skipped), {} level-0 voxels, {} blocks on {} levels, {} bytes -> {}",
                r.id,
                r.seconds,
                r.triangles,
                r.skipped_triangles,
                r.voxels,
                r.blocks,
                r.levels,
                r.bytes,
                r.scene_dir.display()
            );
            println!("resolution {}: {}", r.resolution_choice.resolution, r.resolution_choice.reason);
            Ok(())
        }
        Command::Synth { triangles, out } => {
            let r = voxstream::synth::write_sphere_ply(&out, triangles)
                .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", out.display()))?;
            println!(
                "wrote {}: {} triangles, {} vertices, {} bytes",
                out.display(),
                r.triangles,
                r.vertices,
                r.bytes
            );
            Ok(())
        }
        Command::Bench(args) => voxstream::bench::bench_main(&args),
        Command::BenchMeshopt(args) => voxstream::bench::bench_meshopt_main(&args),
        Command::Serve(args) => voxstream::http::serve_command(args),
    }
}
