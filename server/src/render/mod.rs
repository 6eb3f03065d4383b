//! `voxstream render`: one view of a stored scene rendered offscreen by the
//! viewer's own code (selection, decode, GPU expansion, the same WGSL) with the
//! G-buffer pass, and written out with what the AO was computed for, so any
//! ray tracer can compute a reference at exactly those points
//! (`voxstream reference-ao` does).
//!
//! Files in the output directory: `image.png`, `ao.f32` (W·H LE f32, rows top
//! to bottom, V in [0, 1], NaN on the background), `position.f64` (W·H·3 LE
//! f64, source coordinates), `normal.f32` (W·H·3 LE f32, unit), `render.json`
//! ([`RenderInfo`]).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail, ensure};
use glam::{DMat4, DVec3, DVec4, Mat4};
use serde::{Deserialize, Serialize};
use voxstream_format::Manifest;
use voxstream_viewer::ao::{AoMode, AoSettings, AoStructure, cells_for_grid, cone_directions};
use voxstream_viewer::offscreen::{Offscreen, RenderOptions};
use voxstream_viewer::scene::FixedView;

/// `camera.json`: a perspective camera in the scene's source coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    pub eye: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub fov_y_deg: f64,
    pub near: f64,
    pub far: f64,
}

impl CameraSpec {
    /// Parses and checks a camera.json; every problem is an error naming it.
    pub fn from_json(bytes: &[u8]) -> anyhow::Result<Self> {
        let c: CameraSpec = serde_json::from_slice(bytes).context(
            "camera.json must be {\"eye\":[x,y,z],\"target\":[x,y,z],\"up\":[x,y,z],\"fov_y_deg\":f,\"near\":n,\"far\":f}",
        )?;
        c.validate()?;
        Ok(c)
    }

    pub fn validate(&self) -> anyhow::Result<()> {
        let all = self.eye.iter().chain(&self.target).chain(&self.up).chain([
            &self.fov_y_deg,
            &self.near,
            &self.far,
        ]);
        ensure!(all.into_iter().all(|v| v.is_finite()), "camera: every value must be a finite number");
        let forward = DVec3::from(self.target) - DVec3::from(self.eye);
        ensure!(forward.length() > 0.0, "camera: eye and target are the same point");
        let up = DVec3::from(self.up);
        ensure!(up.length() > 0.0, "camera: up is the zero vector");
        ensure!(
            forward.normalize().cross(up.normalize()).length() > 1e-6,
            "camera: up is parallel to the view direction"
        );
        ensure!(
            self.fov_y_deg > 0.0 && self.fov_y_deg < 180.0,
            "camera: fov_y_deg must be in (0, 180), got {}",
            self.fov_y_deg
        );
        ensure!(
            self.near > 0.0 && self.far > self.near,
            "camera: need 0 < near < far, got near {} far {}",
            self.near,
            self.far
        );
        Ok(())
    }

    /// Unit direction of the ray through pixel centre (x + 0.5, y + 0.5) of a
    /// `width`×`height` image (row 0 at the top), in source coordinates.
    pub fn pixel_ray(&self, width: u32, height: u32, x: u32, y: u32) -> DVec3 {
        let (s, u, f) = self.basis();
        let tan = (self.fov_y_deg.to_radians() * 0.5).tan();
        let aspect = width as f64 / height as f64;
        let ndc_x = ((x as f64 + 0.5) / width as f64) * 2.0 - 1.0;
        let ndc_y = 1.0 - ((y as f64 + 0.5) / height as f64) * 2.0;
        (f + s * (ndc_x * tan * aspect) + u * (ndc_y * tan)).normalize()
    }

    /// Right, up and forward unit vectors (right-handed look-at).
    fn basis(&self) -> (DVec3, DVec3, DVec3) {
        let f = (DVec3::from(self.target) - DVec3::from(self.eye)).normalize();
        let s = f.cross(DVec3::from(self.up)).normalize();
        let u = s.cross(f);
        (s, u, f)
    }

    /// Grid units → wgpu clip space (depth 0..1) for a `width`×`height` view of
    /// a scene whose grid frame is `origin` and `voxel_size`. Built in f64: the
    /// eye is converted to grid units ((p − origin) / voxel_size) before
    /// anything is rounded to f32, so georeferenced scenes stay precise.
    pub fn view_proj_grid(&self, origin: [f64; 3], voxel_size: f64, width: u32, height: u32) -> DMat4 {
        let to_grid = |p: [f64; 3]| (DVec3::from(p) - DVec3::from(origin)) / voxel_size;
        let eye = to_grid(self.eye);
        let (s, u, f) = self.basis();
        let view = DMat4::from_cols(
            DVec4::new(s.x, u.x, -f.x, 0.0),
            DVec4::new(s.y, u.y, -f.y, 0.0),
            DVec4::new(s.z, u.z, -f.z, 0.0),
            DVec4::new(-s.dot(eye), -u.dot(eye), f.dot(eye), 1.0),
        );
        let (near, far) = (self.near / voxel_size, self.far / voxel_size);
        let h = 1.0 / (self.fov_y_deg.to_radians() * 0.5).tan();
        let w = h * height as f64 / width as f64;
        let r = far / (near - far);
        let proj = DMat4::from_cols(
            DVec4::new(w, 0.0, 0.0, 0.0),
            DVec4::new(0.0, h, 0.0, 0.0),
            DVec4::new(0.0, 0.0, r, -1.0),
            DVec4::new(0.0, 0.0, r * near, 0.0),
        );
        proj * view
    }
}

impl CameraSpec {
    /// The viewer's fixed view (grid units) for a `width`×`height` image of a
    /// scene whose grid frame is `origin` and `voxel_size`.
    pub fn fixed_view(
        &self,
        origin: [f64; 3],
        voxel_size: f64,
        width: u32,
        height: u32,
    ) -> anyhow::Result<FixedView> {
        let view_proj = self.view_proj_grid(origin, voxel_size, width, height);
        ensure!(view_proj.is_finite(), "camera: the view matrix is not finite in grid units");
        let eye = (DVec3::from(self.eye) - DVec3::from(origin)) / voxel_size;
        Ok(FixedView {
            view_proj: Mat4::from_cols_array(&view_proj.to_cols_array().map(|v| v as f32)),
            eye: eye.as_vec3(),
            focal_pixels: (height as f64 / (2.0 * (self.fov_y_deg.to_radians() * 0.5).tan())) as f32,
        })
    }
}

/// The AO settings of a render, in source units, as recorded in render.json.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AoRecord {
    /// "cone" (cone tracing) or "field" (the precomputed AO field; R and λ
    /// are then the field's).
    pub mode: String,
    /// The scene's AO field (R in source units) when the mode is "field"; `None`
    /// when the scene has none (every pixel was then cone-traced).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<FieldRecord>,
    /// R in source units.
    pub max_distance: f64,
    /// λ.
    pub falloff: f64,
    pub cones: u32,
    pub aperture_deg: f64,
    /// Step along a cone as a fraction of its diameter.
    pub step: f64,
    /// Start offset along the normal, in source units and in finest occupancy cells.
    pub offset: f64,
    pub offset_cells: f64,
    pub empty_skip: bool,
    pub ignore_normal: bool,
    /// Always true: the sampler filters linearly between mips (quadrilinear).
    pub quadrilinear: bool,
    /// "clipmap" or "volume": what the cones were traced through.
    #[serde(default)]
    pub structure: String,
    /// The clipmap's parameters when it was traced.
    #[serde(default)]
    pub clipmap: Option<ClipmapRecord>,
    /// Finest occupancy cells per grid edge (grid / finest cell) and the
    /// finest cell's edge in source units (the clipmap's finest level, or the volume's cell).
    pub occupancy_cells: u32,
    pub occupancy_cell_size: f64,
    /// Cone axes in the local frame (x, y tangent, z normal), equal weights
    /// (frame 0's set; with jitter each later frame turns it).
    pub cone_directions: Vec<[f32; 3]>,
    /// AO traced for one pixel of each f×f block (1: every pixel).
    pub trace_downscale: u32,
    /// "bilateral" (joint, depth and normal guided) or "bilinear".
    pub upsample: voxstream_viewer::ao::Upsample,
    /// The cone set turned (and the traced pixel moved) every frame.
    pub jitter: bool,
    /// Each traced pixel turns the cone set by its own angle as well.
    pub interleave: bool,
    /// Frames of the still view drawn from a fresh history and averaged
    /// (temporal accumulation with weight 1/frames); 1: a single frame.
    pub frames: u32,
}

/// The occupancy clipmap's parameters in a render (viewer-wasm/src/clipmap.rs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClipmapRecord {
    /// Cells per level edge.
    pub cells: u32,
    pub levels: u32,
    /// Cell edge per level, finest first, in source units (each twice the last).
    pub cell_sizes: Vec<f64>,
    /// Finest cell in grid units (the finest drawn voxel, a power of two).
    pub finest_cell_grid: u32,
    /// Each level's region: its first and one-past-last corner in source units.
    pub regions: Vec<[[f64; 3]; 2]>,
    /// Bytes of cells on the GPU (all levels) and of the source blocks' voxel words.
    pub gpu_bytes: u64,
    /// Fixed-point opacity 1 in a cell.
    pub density_one: u32,
    /// Blocks splatted into the levels (in or out) and compute submissions,
    /// over the whole render (a still camera: the first frame's build).
    pub splats: u64,
    pub updates: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Timings {
    /// Median frame with AO (ms), every selected block drawn; `null` when not timed.
    pub frame_ms: Option<f64>,
    /// Median frame of the same view with AO off (ms).
    pub frame_no_ao_ms: Option<f64>,
    /// frame_ms − frame_no_ao_ms: the AO passes (trace, upsample, temporal) and the G-buffer's extra cost.
    pub ao_pass_ms: Option<f64>,
    /// ao_pass_ms / frame_no_ao_ms.
    pub ao_over_frame: Option<f64>,
    pub runs: usize,
    /// GPU time (timestamp queries) of each pass of the frame with AO, median
    /// per pass, in frame order; absent where the adapter has no timestamps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu_passes_ms: Option<Vec<PassMs>>,
    /// The same for the frame with AO off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu_passes_no_ao_ms: Option<Vec<PassMs>>,
    /// GPU time of the AO passes (trace, upsample, temporal) in the frame with AO.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu_ao_ms: Option<f64>,
    /// GPU time of every timed pass of the frame without AO (the G-buffer draw,
    /// the composite and the depth reduce).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu_frame_no_ao_ms: Option<f64>,
}

/// One pass's median GPU time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PassMs {
    pub pass: String,
    pub ms: f64,
}

impl Timings {
    /// Timings of a frame with AO and one without, timed by `with` and `without`.
    pub fn from_frames(
        with: &voxstream_viewer::offscreen::FrameTiming,
        without: &voxstream_viewer::offscreen::FrameTiming,
        runs: usize,
    ) -> Self {
        let listed = |t: &voxstream_viewer::offscreen::FrameTiming| {
            t.gpu_passes
                .as_ref()
                .map(|p| p.iter().map(|x| PassMs { pass: x.label.to_string(), ms: x.ms }).collect::<Vec<_>>())
        };
        let gpu_passes_ms = listed(with);
        let gpu_passes_no_ao_ms = listed(without);
        let gpu_ao_ms = gpu_passes_ms.as_ref().map(|p| {
            p.iter()
                .filter(|x| voxstream_viewer::shaders::AoPass::is_ao_only_label(&x.pass))
                .map(|x| x.ms)
                .sum()
        });
        let gpu_frame_no_ao_ms = gpu_passes_no_ao_ms.as_ref().map(|p| p.iter().map(|x| x.ms).sum());
        let (w, wo) = (with.cpu_ms, without.cpu_ms);
        Timings {
            frame_ms: Some(w),
            frame_no_ao_ms: Some(wo),
            ao_pass_ms: Some(w - wo),
            ao_over_frame: Some((w - wo) / wo),
            runs,
            gpu_passes_ms,
            gpu_passes_no_ao_ms,
            gpu_ao_ms,
            gpu_frame_no_ao_ms,
        }
    }

    /// No timing asked for.
    pub fn none() -> Self {
        Timings {
            frame_ms: None,
            frame_no_ao_ms: None,
            ao_pass_ms: None,
            ao_over_frame: None,
            runs: 0,
            gpu_passes_ms: None,
            gpu_passes_no_ao_ms: None,
            gpu_ao_ms: None,
            gpu_frame_no_ao_ms: None,
        }
    }
}

/// render.json.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderInfo {
    pub width: u32,
    pub height: u32,
    pub camera: CameraSpec,
    /// Edge of a level-0 voxel in source units.
    pub voxel_size: f64,
    pub grid_origin: [f64; 3],
    pub grid_resolution: u32,
    pub ao: AoRecord,
    pub timings: Timings,
    pub adapter: String,
    pub blocks_drawn: usize,
    /// Levels of the drawn blocks (finest first).
    pub levels_drawn: Vec<u8>,
    /// Pixels with a surface.
    pub surface_pixels: usize,
}

/// The AO field a "field" render showed (`Manifest::ao_field`, R in source units).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldRecord {
    pub cells: u32,
    pub cell_size: f64,
    pub max_distance: f64,
    pub falloff: f64,
    /// Surface pixels that showed the field (the rest were cone-traced).
    pub pixels: usize,
}

/// One view's outputs in memory (source units).
#[derive(Debug, Clone)]
pub struct RenderOutput {
    pub info: RenderInfo,
    /// RGBA8 rows top to bottom.
    pub rgba: Vec<u8>,
    pub ao: Vec<f32>,
    pub position: Vec<[f64; 3]>,
    pub normal: Vec<[f32; 3]>,
}

/// What `voxstream render` needs.
#[derive(Debug, Clone)]
pub struct RenderRequest {
    pub scene_dir: PathBuf,
    pub camera: CameraSpec,
    pub width: u32,
    pub height: u32,
    pub ao: AoSettings,
    /// R in source units (overrides `ao.max_distance`, which is in grid units).
    pub max_distance: Option<f64>,
    /// Timed frames per setting (0: no timing).
    pub timing_runs: usize,
    /// Frames of the still view accumulated (jittered when `ao.jitter`): the
    /// AO written is their average. 1: one frame.
    pub ao_frames: u32,
}

/// Largest image edge `render` accepts.
pub const MAX_EDGE: u32 = 8192;

/// Renders one view.
pub fn render_view(req: &RenderRequest) -> anyhow::Result<RenderOutput> {
    ensure!(
        (1..=MAX_EDGE).contains(&req.width) && (1..=MAX_EDGE).contains(&req.height),
        "--width and --height must be 1..={MAX_EDGE}, got {}x{}",
        req.width,
        req.height
    );
    req.camera.validate()?;
    let manifest_path = req.scene_dir.join("manifest.json");
    ensure!(
        manifest_path.is_file(),
        "{} is not a scene directory (no manifest.json); pass --scene <store>/<scene-id>",
        req.scene_dir.display()
    );
    let manifest = Manifest::from_json(
        &std::fs::read(&manifest_path).with_context(|| format!("reading {}", manifest_path.display()))?,
    )
    .with_context(|| format!("{} is not a valid manifest", manifest_path.display()))?;
    let grid = manifest.grid.clone();
    let mut ao = req.ao;
    if let Some(r) = req.max_distance {
        ensure!(r.is_finite() && r > 0.0, "--max-distance must be a positive number, got {r}");
        ao.max_distance = Some((r / grid.voxel_size) as f32);
    }
    // The field was computed for one R and λ: the render (and its fallback cones) uses those.
    let field_info = manifest.ao_field.clone().filter(|_| ao.mode == AoMode::Field);
    if let Some(f) = &field_info {
        ao.max_distance = Some(f.max_distance);
        ao.falloff = f.falloff;
    }
    let (w, h) = (req.width, req.height);
    let mut offscreen = Offscreen::open(&req.scene_dir, &RenderOptions::new(w, h))?;
    offscreen.scene.fixed_view = Some(req.camera.fixed_view(grid.origin, grid.voxel_size, w, h)?);
    let frames = req.ao_frames.clamp(1, voxstream_viewer::ao::MAX_TEMPORAL_FRAMES);
    ao.temporal_frames = frames;
    offscreen.renderer.ao = ao;
    let g = offscreen.render_gbuffer(frames)?;
    if !g.frame.failures.is_empty() {
        bail!("blocks failed to load: {:?}", g.frame.failures);
    }
    let timings = if req.timing_runs > 0 {
        let with = offscreen.time_frames(1.0, req.timing_runs)?;
        let without = offscreen.time_frames(0.0, req.timing_runs)?;
        Timings::from_frames(&with, &without, req.timing_runs)
    } else {
        Timings::none()
    };
    let n = (w * h) as usize;
    let mut ao_out = vec![f32::NAN; n];
    let mut position = vec![[f64::NAN; 3]; n];
    let mut normal = vec![[f32::NAN; 3]; n];
    let mut surface_pixels = 0;
    for i in 0..n {
        let p = g.position_ao[i];
        let na = g.normal[i];
        if na[3] < 0.5 {
            continue;
        }
        let nv = glam::Vec3::new(na[0], na[1], na[2]);
        // The shader writes finite values; anything else stays NaN (no surface).
        if !(p.iter().all(|v| v.is_finite()) && nv.is_finite() && nv.length() > 0.5) {
            continue;
        }
        surface_pixels += 1;
        ao_out[i] = p[3].clamp(0.0, 1.0);
        position[i] = std::array::from_fn(|a| grid.origin[a] + p[a] as f64 * grid.voxel_size);
        normal[i] = nv.normalize_or(glam::Vec3::Z).to_array();
    }
    let clipmap_layout = offscreen.renderer.clipmap.layout().filter(|_| ao.structure == AoStructure::Clipmap);
    let (cells, finest_cell) = match clipmap_layout {
        Some(l) => ((grid.resolution / l.finest_cell).max(1), l.finest_cell as f32),
        None => (cells_for_grid(grid.resolution), voxstream_viewer::ao::volume_cell(grid.resolution)),
    };
    let uniform = ao.uniform_jittered(grid.resolution, finest_cell, voxstream_viewer::ao::ConeJitter::NONE);
    let cell_size = finest_cell as f64 * grid.voxel_size;
    let clipmap = clipmap_layout.map(|l| {
        let c = &offscreen.renderer.clipmap;
        let regions = c
            .levels()
            .iter()
            .enumerate()
            .map(|(k, level)| {
                let edge = l.cell(k as u32) as f64;
                let o = level.origin.unwrap_or([0; 3]);
                let at = |shift: i32| {
                    std::array::from_fn(|a| grid.origin[a] + (o[a] + shift) as f64 * edge * grid.voxel_size)
                };
                [at(0), at(l.cells as i32)]
            })
            .collect();
        ClipmapRecord {
            cells: l.cells,
            levels: l.levels,
            cell_sizes: (0..l.levels).map(|k| l.cell(k) as f64 * grid.voxel_size).collect(),
            finest_cell_grid: l.finest_cell,
            regions,
            gpu_bytes: c.gpu_bytes(),
            density_one: voxstream_viewer::clipmap::DENSITY_ONE,
            splats: c.counters.splats,
            updates: c.counters.updates,
        }
    });
    let mut levels: Vec<u8> = g.frame.drawn_blocks.iter().map(|k| k.level).collect();
    levels.sort();
    levels.dedup();
    let info = RenderInfo {
        width: w,
        height: h,
        camera: req.camera,
        voxel_size: grid.voxel_size,
        grid_origin: grid.origin,
        grid_resolution: grid.resolution,
        ao: AoRecord {
            mode: ao.mode.name().into(),
            field: field_info.map(|f| FieldRecord {
                cells: f.cells,
                cell_size: grid.resolution as f64 / f.cells as f64 * grid.voxel_size,
                max_distance: f.max_distance as f64 * grid.voxel_size,
                falloff: f.falloff as f64,
                pixels: g.field_pixels,
            }),
            max_distance: uniform.range[0] as f64 * grid.voxel_size,
            falloff: uniform.range[1] as f64,
            cones: ao.cone_count(),
            aperture_deg: ao.aperture() as f64,
            step: uniform.cone[2] as f64,
            offset: uniform.cone[3] as f64 * grid.voxel_size,
            offset_cells: uniform.cone[3] as f64 * grid.voxel_size / cell_size,
            empty_skip: ao.empty_skip,
            ignore_normal: ao.ignore_normal,
            quadrilinear: true,
            structure: if clipmap.is_some() { "clipmap" } else { "volume" }.into(),
            clipmap,
            occupancy_cells: cells,
            occupancy_cell_size: cell_size,
            cone_directions: cone_directions(ao.cone_count()),
            trace_downscale: ao.downscale(),
            upsample: ao.upsample,
            jitter: ao.jitter,
            interleave: ao.interleave,
            frames,
        },
        timings,
        adapter: g.frame.adapter.clone(),
        blocks_drawn: g.frame.drawn_blocks.len(),
        levels_drawn: levels,
        surface_pixels,
    };
    Ok(RenderOutput { info, rgba: g.frame.pixels, ao: ao_out, position, normal })
}

/// Writes the five files into `dir` (created if missing).
pub fn write_outputs(dir: &Path, out: &RenderOutput) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let (w, h) = (out.info.width, out.info.height);
    write_png_rgba(&dir.join("image.png"), w, h, &out.rgba)?;
    write_file(&dir.join("ao.f32"), &f32_bytes(&out.ao))?;
    let pos: Vec<u8> = out.position.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    write_file(&dir.join("position.f64"), &pos)?;
    let nrm: Vec<f32> = out.normal.iter().flatten().copied().collect();
    write_file(&dir.join("normal.f32"), &f32_bytes(&nrm))?;
    let json = serde_json::to_vec_pretty(&out.info)?;
    write_file(&dir.join("render.json"), &json)?;
    Ok(())
}

/// render.json, ao.f32, position.f64 and normal.f32 as read back.
pub type RenderFiles = (RenderInfo, Vec<f32>, Vec<[f64; 3]>, Vec<[f32; 3]>);

/// Reads back what [`write_outputs`] wrote, checking every size.
pub fn read_outputs(dir: &Path) -> anyhow::Result<RenderFiles> {
    let read = |name: &str| {
        let p = dir.join(name);
        std::fs::read(&p)
            .with_context(|| format!("reading {} (is --render a `voxstream render` output?)", p.display()))
    };
    let info: RenderInfo = serde_json::from_slice(&read("render.json")?)
        .with_context(|| format!("{} is not a render.json", dir.join("render.json").display()))?;
    ensure!(
        (1..=MAX_EDGE).contains(&info.width) && (1..=MAX_EDGE).contains(&info.height),
        "render.json: bad size {}x{}",
        info.width,
        info.height
    );
    info.camera.validate()?;
    ensure!(
        info.ao.max_distance.is_finite()
            && info.ao.max_distance > 0.0
            && info.ao.falloff.is_finite()
            && info.ao.falloff >= 0.0,
        "render.json: ao.max_distance must be > 0 and ao.falloff >= 0"
    );
    let n = (info.width * info.height) as usize;
    let ao = read("ao.f32")?;
    ensure!(
        ao.len() == n * 4,
        "ao.f32 has {} bytes, expected {} for {}x{}",
        ao.len(),
        n * 4,
        info.width,
        info.height
    );
    let pos = read("position.f64")?;
    ensure!(pos.len() == n * 24, "position.f64 has {} bytes, expected {}", pos.len(), n * 24);
    let nrm = read("normal.f32")?;
    ensure!(nrm.len() == n * 12, "normal.f32 has {} bytes, expected {}", nrm.len(), n * 12);
    let f32s = |b: &[u8]| -> Vec<f32> {
        b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4"))).collect()
    };
    let ao = f32s(&ao);
    let position = pos
        .chunks_exact(24)
        .map(|c| std::array::from_fn(|a| f64::from_le_bytes(c[a * 8..a * 8 + 8].try_into().expect("8"))))
        .collect();
    let normal = f32s(&nrm).chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    Ok((info, ao, position, normal))
}

pub fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

pub fn write_file(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

pub fn write_png_rgba(path: &Path, w: u32, h: u32, rgba: &[u8]) -> anyhow::Result<()> {
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.write_header()?.write_image_data(rgba)?;
    Ok(())
}

/// A grey image of values in [0, 1] (NaN: the background colour), as RGBA8.
pub fn grey_rgba(values: &[f32]) -> Vec<u8> {
    values
        .iter()
        .flat_map(|&v| {
            if v.is_finite() {
                let g = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
                [g, g, g, 255]
            } else {
                voxstream_viewer::BACKGROUND_RGBA8
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera_json(eye: &str, fov: &str) -> String {
        format!(r#"{{"eye":{eye},"target":[0,0,0],"up":[0,1,0],"fov_y_deg":{fov},"near":0.1,"far":100}}"#)
    }

    #[test]
    fn bad_cameras_are_errors_naming_the_problem() {
        CameraSpec::from_json(camera_json("[0,0,5]", "45").as_bytes()).unwrap();
        for (json, needle) in [
            (camera_json("[0,0,0]", "45"), "same point"),
            (camera_json("[0,5,0]", "45"), "parallel"),
            (camera_json("[0,0,5]", "180"), "fov_y_deg"),
            (camera_json("[0,0,5]", "-1"), "fov_y_deg"),
            (camera_json("[0,0]", "45"), "camera.json must be"),
            ("{\"eye\":[0,0,1]}".to_string(), "camera.json must be"),
            ("not json".to_string(), "camera.json must be"),
            (camera_json("[0,0,5]", "45").replace("\"near\":0.1", "\"near\":200"), "near"),
        ] {
            let e = CameraSpec::from_json(json.as_bytes()).expect_err(&json);
            assert!(format!("{e:#}").contains(needle), "{json}: {e:#}");
        }
    }

    #[test]
    fn view_matrix_puts_the_target_at_the_centre_and_is_translation_exact() {
        let c = CameraSpec {
            eye: [3.0, 2.0, 5.0],
            target: [1.0, 1.0, 1.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
            near: 0.1,
            far: 50.0,
        };
        let m = c.view_proj_grid([0.0; 3], 0.5, 200, 100);
        let t = m * DVec4::new(2.0, 2.0, 2.0, 1.0); // target in grid units
        assert!((t.x / t.w).abs() < 1e-12 && (t.y / t.w).abs() < 1e-12);
        // The same camera and scene moved by 1e6: identical grid-space matrix.
        let moved = CameraSpec {
            eye: [1e6 + 3.0, 2.0 - 1e6, 5.0 + 1e6],
            target: [1e6 + 1.0, 1.0 - 1e6, 1.0 + 1e6],
            ..c
        };
        let m2 = moved.view_proj_grid([1e6, -1e6, 1e6], 0.5, 200, 100);
        assert!(m.abs_diff_eq(m2, 1e-9), "{m} vs {m2}");
        // The pixel ray through the centre is the view direction; row 0 looks up.
        let centre = c.pixel_ray(201, 101, 100, 50);
        let f = (DVec3::from(c.target) - DVec3::from(c.eye)).normalize();
        assert!((centre - f).length() < 1e-12);
        assert!(c.pixel_ray(201, 101, 100, 0).y > centre.y);
    }

    #[test]
    fn wrong_sizes_and_missing_files_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let e = read_outputs(dir.path()).unwrap_err();
        assert!(format!("{e:#}").contains("render.json"), "{e:#}");
        let out = RenderOutput {
            info: RenderInfo {
                width: 2,
                height: 1,
                camera: CameraSpec::from_json(camera_json("[0,0,5]", "45").as_bytes()).unwrap(),
                voxel_size: 0.1,
                grid_origin: [0.0; 3],
                grid_resolution: 64,
                ao: AoRecord {
                    mode: "cone".into(),
                    field: None,
                    max_distance: 1.0,
                    falloff: 1.0,
                    cones: 16,
                    aperture_deg: 14.5,
                    step: 0.5,
                    offset: 0.1,
                    offset_cells: 1.5,
                    empty_skip: true,
                    ignore_normal: false,
                    quadrilinear: true,
                    structure: "clipmap".into(),
                    clipmap: None,
                    occupancy_cells: 64,
                    occupancy_cell_size: 0.1,
                    cone_directions: vec![],
                    trace_downscale: 2,
                    upsample: voxstream_viewer::ao::Upsample::Bilateral,
                    jitter: true,
                    interleave: true,
                    frames: 8,
                },
                timings: Timings {
                    gpu_passes_ms: Some(vec![PassMs { pass: "cs_trace".into(), ms: 0.25 }]),
                    gpu_ao_ms: Some(0.25),
                    ..Timings::none()
                },
                adapter: "test".into(),
                blocks_drawn: 0,
                levels_drawn: vec![],
                surface_pixels: 1,
            },
            rgba: vec![0; 8],
            ao: vec![0.5, f32::NAN],
            position: vec![[1.0, 2.0, 3.0], [f64::NAN; 3]],
            normal: vec![[0.0, 1.0, 0.0], [f32::NAN; 3]],
        };
        write_outputs(dir.path(), &out).unwrap();
        let (info, ao, pos, nrm) = read_outputs(dir.path()).unwrap();
        assert_eq!(info, out.info);
        assert_eq!(ao[0], 0.5);
        assert!(ao[1].is_nan() && pos[1][0].is_nan() && nrm[1][2].is_nan());
        assert_eq!(pos[0], [1.0, 2.0, 3.0]);
        std::fs::write(dir.path().join("ao.f32"), [0u8; 4]).unwrap();
        let e = read_outputs(dir.path()).unwrap_err();
        assert!(format!("{e:#}").contains("ao.f32 has 4 bytes"), "{e:#}");
    }
}
