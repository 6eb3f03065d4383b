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
        /// The store directory; the scene is published as <out>/<name>. Or s3://bucket/prefix:
        /// packs and pages are uploaded as they are finished and <prefix>/<name>/manifest.json
        /// last (endpoint and credentials from AWS_* variables or VOXSTREAM_S3_ENV_FILE).
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
        /// Directory for the build's temporary files (default: inside --out; the system's temp
        /// folder for an s3:// --out); removed afterwards.
        #[arg(long)]
        tmp: Option<PathBuf>,
        /// Compute the precomputed AO field (seed 002; issue 9 item 2): each drawn voxel carries
        /// one byte of visibility for the viewer's `field` AO mode (about 30 % more bytes a block).
        /// Without it that mode falls back to cone tracing.
        #[arg(long)]
        ao_field: bool,
        /// Cells per edge of the AO field's whole-grid occupancy (at most the resolution);
        /// its peak memory (≈ 19 B a cell) must fit the budget beside the build's smallest plan.
        #[arg(long, default_value_t = 128, value_parser = clap::value_parser!(u32).range(2..=512))]
        ao_field_cells: u32,
        /// Distinct values the AO field's V is rounded to (2..=255; fewer compress better).
        #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(2..=255))]
        ao_field_levels: u32,
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
    /// Write a scene and the viewer as a static site (any static file host serves it).
    Publish {
        /// The scene id.
        scene: String,
        /// The store holding the scene.
        #[arg(long)]
        store: PathBuf,
        /// The folder to write (replaced whole if it holds an earlier publish), or s3://bucket/prefix
        /// (endpoint and credentials from AWS_* variables or VOXSTREAM_S3_ENV_FILE).
        #[arg(long)]
        to: String,
        /// Take the viewer's files from this built folder instead of the ones in this binary.
        #[arg(long)]
        web: Option<PathBuf>,
    },
    /// Render one view of a stored scene offscreen (Vulkan; lavapipe without a GPU) and write
    /// image.png, ao.f32, position.f64, normal.f32 and render.json.
    Render(RenderArgs),
    /// Benchmark the cone-traced AO: run time against error over a sweep of settings on the
    /// analytic scenes and the named views; writes docs/ao-benchmark.md and docs/ao-pareto.png.
    AoBench(voxstream::reference::bench::AoBenchArgs),
    /// Ray-trace the AO reference on the CPU at the points a `render` wrote, against the
    /// original mesh; writes reference.f32, reference_stderr.f32, reference.png, primary.f32
    /// and compare.json.
    ReferenceAo {
        /// The original mesh the scene was built from.
        #[arg(long)]
        mesh: PathBuf,
        /// A `voxstream render` output directory.
        #[arg(long)]
        render: PathBuf,
        /// Cosine-weighted rays per pixel.
        #[arg(long, default_value_t = voxstream::reference::DEFAULT_RAYS)]
        rays: u32,
        /// Skip the ray-traced view of the mesh (primary rays through each pixel).
        #[arg(long)]
        no_primary: bool,
        /// Trace against this stored scene's level-0 voxels (its exposed faces)
        /// instead of the mesh: the AO of the voxelized geometry, which the cone
        /// tracer estimates (the rest of its error against the mesh is the
        /// voxelization's).
        #[arg(long, value_name = "SCENE_DIR")]
        voxels: Option<PathBuf>,
    },
}

#[derive(clap::Args)]
struct RenderArgs {
    /// The scene directory, <store>/<scene-id>.
    #[arg(long)]
    scene: PathBuf,
    /// camera.json: {"eye":[x,y,z],"target":[x,y,z],"up":[x,y,z],"fov_y_deg":f,"near":n,"far":f}
    /// in the scene's source coordinates.
    #[arg(long)]
    camera: PathBuf,
    #[arg(long)]
    width: u32,
    #[arg(long)]
    height: u32,
    /// Output directory (created).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    ao: AoArgs,
    /// Timed frames with and without AO (median reported; 0: no timing).
    #[arg(long, default_value_t = 3)]
    timing_runs: usize,
    /// Frames of the still camera to accumulate (temporal accumulation from a
    /// fresh history, each frame's cone set jittered unless --no-jitter): the
    /// AO written is their average. Default: the viewer's (what a still view
    /// converges to in the browser).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=256))]
    ao_frames: Option<u32>,
}

/// Cone-traced AO settings. Every one left out is the viewer's own default
/// (viewer-wasm/src/ao.rs, `AoSettings::default()`), so a plain `render` shows
/// what the browser shows.
#[derive(clap::Args)]
struct AoArgs {
    /// Cones per pixel: 3, 5, 6, 8 or 16 (viewer default 6).
    #[arg(long, value_parser = parse_cones)]
    cones: Option<u32>,
    /// Cone half-angle in degrees (default: asin(1/sqrt(cones))).
    #[arg(long)]
    aperture_deg: Option<f32>,
    /// Step along a cone as a fraction of its diameter (viewer default 0.7).
    #[arg(long)]
    step: Option<f32>,
    /// Start offset along the normal, in finest occupancy cells (viewer default 1.5).
    #[arg(long)]
    offset_cells: Option<f32>,
    /// R, the AO's maximum distance, in source units (default: a tenth of the scene's bounding cube edge).
    #[arg(long)]
    max_distance: Option<f64>,
    /// λ in w(d) = 1 / (1 + λ·d/R) (viewer default 1).
    #[arg(long)]
    falloff: Option<f32>,
    /// Skip empty space (hierarchical steps through coarse empty cells; off in the viewer).
    #[arg(long, conflicts_with = "no_empty_skip")]
    empty_skip: bool,
    /// No empty-space skipping (the viewer's default; kept for older command lines).
    #[arg(long, hide = true)]
    no_empty_skip: bool,
    /// Negative control: lay the cones around +Z whatever the surface normal.
    #[arg(long, hide = true)]
    ignore_normal: bool,
    /// Trace AO for one pixel of each f×f block and upsample (1 = every pixel, 2, 4; viewer default 2).
    #[arg(long, value_parser = parse_downscale)]
    ao_downscale: Option<u32>,
    /// Upsampling of a reduced-resolution trace.
    #[arg(long, value_enum, default_value_t = UpsampleArg::Bilateral)]
    ao_upsample: UpsampleArg,
    /// Keep the cone set fixed: no rotation from frame to frame (with
    /// --ao-frames) and none from pixel to pixel (interleaved sampling).
    #[arg(long)]
    no_jitter: bool,
    /// The occupancy structure the cones trace: the clipmap (nested levels
    /// around the camera, built on the GPU) or the single volume of at most
    /// 128³ cells (comparison).
    #[arg(long, value_enum, default_value_t = StructureArg::Clipmap)]
    ao_structure: StructureArg,
    /// How V is computed: cone tracing, or the precomputed AO field the scene's
    /// blocks carry (built by `voxstream build`; R and λ are then the field's,
    /// from the manifest, and pixels without a field are cone-traced).
    #[arg(long, value_enum, default_value_t = ModeArg::Cone)]
    ao_mode: ModeArg,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ModeArg {
    Cone,
    Field,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum StructureArg {
    Clipmap,
    Volume,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum UpsampleArg {
    /// Joint bilateral: bilinear weights times depth and normal likeness; a
    /// pixel no traced texel around it matches is traced itself.
    Bilateral,
    /// Joint bilateral without tracing the pixels it cannot match (comparison).
    BilateralOnly,
    /// Plain bilinear (blurs across depth edges; for comparison).
    Bilinear,
}

fn parse_downscale(s: &str) -> Result<u32, String> {
    match s.parse::<u32>() {
        Ok(n @ (1 | 2 | 4)) => Ok(n),
        _ => Err("must be 1, 2 or 4".into()),
    }
}

fn parse_cones(s: &str) -> Result<u32, String> {
    match s.parse::<u32>() {
        Ok(n) if voxstream_viewer::ao::CONE_COUNTS.contains(&n) => Ok(n),
        _ => Err(format!("must be one of {:?}", voxstream_viewer::ao::CONE_COUNTS)),
    }
}

impl AoArgs {
    fn settings(&self) -> anyhow::Result<voxstream_viewer::ao::AoSettings> {
        let finite = |name: &str, v: f32, ok: bool| {
            anyhow::ensure!(v.is_finite() && ok, "--{name} out of range: {v}");
            Ok(())
        };
        let d = voxstream_viewer::ao::AoSettings::default();
        let (step, offset_cells, falloff) = (
            self.step.unwrap_or(d.step),
            self.offset_cells.unwrap_or(d.offset_cells),
            self.falloff.unwrap_or(d.falloff),
        );
        finite("step", step, step > 0.0)?;
        finite("offset-cells", offset_cells, offset_cells >= 0.0)?;
        finite("falloff", falloff, falloff >= 0.0)?;
        if let Some(a) = self.aperture_deg {
            finite("aperture-deg", a, a > 0.0 && a < 90.0)?;
        }
        Ok(voxstream_viewer::ao::AoSettings {
            cones: self.cones.unwrap_or(d.cones),
            aperture_deg: self.aperture_deg,
            step,
            offset_cells,
            max_distance: None,
            falloff,
            empty_skip: self.empty_skip || (d.empty_skip && !self.no_empty_skip),
            ignore_normal: self.ignore_normal,
            trace_downscale: self.ao_downscale.unwrap_or(d.trace_downscale),
            upsample: match self.ao_upsample {
                UpsampleArg::Bilateral => voxstream_viewer::ao::Upsample::Bilateral,
                UpsampleArg::BilateralOnly => voxstream_viewer::ao::Upsample::BilateralOnly,
                UpsampleArg::Bilinear => voxstream_viewer::ao::Upsample::Bilinear,
            },
            jitter: !self.no_jitter,
            interleave: !self.no_jitter,
            structure: match self.ao_structure {
                StructureArg::Clipmap => voxstream_viewer::ao::AoStructure::Clipmap,
                StructureArg::Volume => voxstream_viewer::ao::AoStructure::Volume,
            },
            mode: match self.ao_mode {
                ModeArg::Cone => voxstream_viewer::ao::AoMode::Cone,
                ModeArg::Field => voxstream_viewer::ao::AoMode::Field,
            },
            ..voxstream_viewer::ao::AoSettings::default()
        })
    }
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

/// `publish` reads a local store only: an `s3://` store is refused by name instead of being taken
/// for a folder called "s3:".
fn no_bucket_store(path: &std::path::Path, flag: &str) -> anyhow::Result<()> {
    if path.to_str().is_some_and(|p| p.contains("://")) {
        anyhow::bail!(
            "{flag} {}: publishing from a bucket is not supported yet, only from a local store \
             (publish --to s3://bucket/prefix writes a static site to a bucket)",
            path.display()
        );
    }
    Ok(())
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Build {
            mesh,
            out,
            resolution,
            voxel_size,
            name,
            topology,
            memory_budget,
            tmp,
            ao_field,
            ao_field_cells,
            ao_field_levels,
        } => {
            let out = voxstream::objstore::parse_location(&out.to_string_lossy())
                .map_err(|e| anyhow::anyhow!("--out {e}"))?;
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
            let opts = BuildOptions {
                resolution,
                name,
                topology,
                cancel: None,
                memory_budget,
                temp_dir: tmp,
                ao_field: ao_field.then(|| voxstream::pipeline::aofield::AoFieldOptions {
                    levels: ao_field_levels,
                    cells: ao_field_cells,
                    ..Default::default()
                }),
                ..Default::default()
            };
            let (result, published_at) = match out {
                voxstream::objstore::Location::Local(dir) => {
                    let r = build_scene_reporting(&mesh, &dir, &opts, &report);
                    let at = r.as_ref().map(|r| r.scene_dir.display().to_string()).unwrap_or_default();
                    (r.map_err(anyhow::Error::from), at)
                }
                voxstream::objstore::Location::S3 { bucket, prefix } => {
                    match voxstream::bucket_build::build_into_bucket(&mesh, &bucket, &prefix, opts, &report) {
                        Ok(b) => {
                            let at = format!("{} ({} objects, {} bytes)", b.url, b.objects, b.bytes);
                            (Ok(b.report), at)
                        }
                        Err(e) => (Err(e), String::new()),
                    }
                }
            };
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
                published_at
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
        Command::Publish { scene, store, to, web } => {
            let viewer = match &web {
                Some(dir) => voxstream::publish::ViewerFiles::Dir(dir),
                None => voxstream::publish::ViewerFiles::Embedded,
            };
            no_bucket_store(&store, "publish --store")?;
            let r = match voxstream::objstore::parse_location(&to).map_err(|e| anyhow::anyhow!("--to {e}"))? {
                voxstream::objstore::Location::Local(dir) => {
                    voxstream::publish::publish(&store, &scene, &dir, viewer)?
                }
                voxstream::objstore::Location::S3 { bucket, prefix } => {
                    let rt = tokio::runtime::Runtime::new()?;
                    rt.block_on(async {
                        let b = voxstream::objstore::connect(
                            &bucket,
                            &prefix,
                            std::time::Duration::from_secs(10),
                        )
                        .await?;
                        voxstream::publish::publish_to_bucket(&store, &scene, &b, viewer).await
                    })?
                }
            };
            println!(
                "published scene {:?} to {}: {} files ({} blocks in {} packs, {} pages), {} bytes",
                r.id,
                r.to.display(),
                r.files,
                r.blocks,
                r.packs,
                r.pages,
                r.bytes
            );
            Ok(())
        }
        Command::Render(args) => {
            let bytes = std::fs::read(&args.camera)
                .map_err(|e| anyhow::anyhow!("cannot read --camera {}: {e}", args.camera.display()))?;
            let camera = voxstream::render::CameraSpec::from_json(&bytes)
                .map_err(|e| anyhow::anyhow!("{}: {e:#}", args.camera.display()))?;
            let ao = args.ao.settings()?;
            let request = voxstream::render::RenderRequest {
                scene_dir: args.scene.clone(),
                camera,
                width: args.width,
                height: args.height,
                ao,
                max_distance: args.ao.max_distance,
                timing_runs: args.timing_runs,
                // A fixed cone set gains nothing from more frames of a still view.
                ao_frames: args.ao_frames.unwrap_or(if ao.jitter { ao.temporal_frames } else { 1 }),
            };
            let out = voxstream::render::render_view(&request)?;
            voxstream::render::write_outputs(&args.out, &out)?;
            println!("{}", serde_json::to_string_pretty(&out.info)?);
            Ok(())
        }
        Command::AoBench(args) => voxstream::reference::bench::ao_bench_main(&args),
        Command::ReferenceAo { mesh, render, rays, no_primary, voxels } => {
            let report = voxstream::reference::reference_command(
                &mesh,
                &render,
                rays,
                !no_primary,
                voxels.as_deref(),
            )?;
            println!("{}", serde_json::to_string_pretty(&report)?);
            Ok(())
        }
    }
}
