//! Scene thumbnails: `GET /api/scenes/{id}/thumbnail.png`, rendered on the CPU.
//!
//! The finest level with at most [`MAX_VOXELS`] voxels is decoded and its
//! exposed faces that look towards a fixed three-quarter camera (+Y up, from
//! +X +Y +Z) are rasterized orthographically into a z-buffer, Lambert-shaded
//! from the stored normal and colour (the viewer's warm grey when a scene has
//! none) over the viewer's background colour. The PNG is cached beside the
//! manifest as `thumbnail-<key>.png`, the key hashing the manifest and the
//! renderer version, so a rebuilt scene (a new directory) or a changed
//! renderer never shows an old picture; a store that cannot be written still
//! gets its thumbnails, rendered on every request.

use std::path::{Path, PathBuf};

use axum::extract::{Path as UrlPath, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use voxstream_format::{BLOCK_SIZE, Block, Face, Manifest, decode_block, oct_decode};

use crate::catalog::LoadedScene;
use crate::http::access::ReadAccess;
use crate::http::{ApiError, AppState};
use crate::store::{StoredScene, validate_id};

/// Edge of the square thumbnail in pixels.
pub const SIZE: u32 = 256;
/// Most voxels decoded for one thumbnail: the level chosen is the finest under this.
pub const MAX_VOXELS: u64 = 100_000;
/// The viewer's clear colour (voxstream_viewer::BACKGROUND_RGBA8), so thumbnails read as the viewer.
pub const BACKGROUND: [u8; 3] = [20, 24, 36];
/// The viewer's base colour for scenes without colour (shaders/voxel.wgsl BASE_COLOUR).
const BASE_COLOUR: [f32; 3] = [0.86, 0.80, 0.72];
/// Bumped whenever the picture for the same scene would change: part of the cache key.
const RENDER_VERSION: &str = "thumbnail-v1";
/// Fraction of the edge left empty on each side.
const MARGIN: f32 = 0.06;

#[derive(Debug, thiserror::Error)]
pub enum ThumbnailError {
    #[error("block {key} of scene {id:?} is unreadable: {message}")]
    Block { id: String, key: String, message: String },
    #[error("scene {0:?} has no voxels to draw")]
    Empty(String),
}

/// An RGB8 image, row-major from the top-left.
#[derive(Debug, Clone)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Image {
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        let i = 3 * (y * self.width + x) as usize;
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }
}

/// The finest level with at most `budget` voxels, or the coarsest level when none has so few.
pub fn thumbnail_level(manifest: &Manifest, budget: u64) -> u8 {
    let mut levels: Vec<_> = manifest.levels.iter().map(|l| (l.level, l.voxels)).collect();
    levels.sort_unstable();
    levels
        .iter()
        .find(|&&(_, voxels)| voxels <= budget)
        .or(levels.last())
        .map_or(manifest.coarsest_level(), |&(level, _)| level)
}

/// Reads and decodes the blocks of one level, checking each against the manifest (hash and key).
pub fn read_level(scene: &StoredScene, level: u8) -> Result<Vec<Block>, ThumbnailError> {
    let fail = |key: String, message: String| ThumbnailError::Block { id: scene.id.clone(), key, message };
    scene
        .blocks()
        .into_iter()
        .filter(|b| b.key.level == level)
        .map(|entry| {
            let key = entry.key.to_string();
            let bytes = scene.read_block(&entry).map_err(|e| match e {
                crate::store::BlockReadError::Changed { .. } => {
                    fail(key.clone(), "its bytes differ from the manifest's hash".into())
                }
                e => fail(key.clone(), e.to_string()),
            })?;
            let block = decode_block(&bytes).map_err(|e| fail(key.clone(), e.to_string()))?;
            if block.key != entry.key {
                return Err(fail(key, format!("the file holds block {}", block.key)));
            }
            Ok(block)
        })
        .collect()
}

type Vec3 = [f32; 3];

fn dot(a: Vec3, b: Vec3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn normalize(a: Vec3) -> Vec3 {
    let len = dot(a, a).sqrt();
    [a[0] / len, a[1] / len, a[2] / len]
}

/// The fixed three-quarter view: towards the camera, screen right, screen up (+Y up).
struct View {
    to_camera: Vec3,
    right: Vec3,
    up: Vec3,
    light: Vec3,
}

impl View {
    fn three_quarter() -> View {
        let to_camera = normalize([0.8, 0.65, 1.0]);
        let right = normalize(cross([0.0, 1.0, 0.0], to_camera));
        let up = cross(to_camera, right);
        // Light from over the viewer's left shoulder.
        let light = normalize([
            to_camera[0] + 0.6 * up[0] - 0.4 * right[0],
            to_camera[1] + 0.6 * up[1] - 0.4 * right[1],
            to_camera[2] + 0.6 * up[2] - 0.4 * right[2],
        ]);
        View { to_camera, right, up, light }
    }

    /// (screen x, screen y, depth towards the camera) in grid units.
    fn project(&self, p: Vec3) -> Vec3 {
        [dot(p, self.right), dot(p, self.up), dot(p, self.to_camera)]
    }
}

/// A voxel in grid units with what shading needs.
struct Splat {
    corner: Vec3,
    size: f32,
    faces: u8,
    normal: Vec3,
    colour: Vec3,
}

fn splats(blocks: &[Block]) -> Vec<Splat> {
    let mut out = Vec::with_capacity(blocks.iter().map(|b| b.voxels.len()).sum());
    for block in blocks {
        let size = (1u64 << block.key.level.min(24)) as f32;
        let coord = block.key.coord();
        for v in &block.voxels {
            let local = v.local();
            let corner =
                std::array::from_fn(|a| (coord[a] as f32 * BLOCK_SIZE as f32 + local[a] as f32) * size);
            let colour = v.color().map_or(BASE_COLOUR, |c| c.map(|x| x as f32 / 255.0));
            out.push(Splat { corner, size, faces: v.faces(), normal: oct_decode(v.normal), colour });
        }
    }
    out
}

/// Renders `blocks` (grid units, any one level) into a `size`² image: each
/// exposed face turned towards the camera is a parallelogram in the
/// z-buffer; the picture is scaled to fit with a margin.
pub fn render(blocks: &[Block], size: u32) -> Image {
    let view = View::three_quarter();
    let splats = splats(blocks);
    let mut rgb: Vec<u8> = BACKGROUND.iter().copied().cycle().take(3 * (size * size) as usize).collect();
    if splats.is_empty() || size == 0 {
        return Image { width: size, height: size, rgb };
    }
    // Fit: the projected bounding box of every voxel's cube.
    let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    for s in &splats {
        let c = view.project(s.corner.map(|x| x + s.size * 0.5));
        let reach = s.size * 0.5 * 3f32.sqrt();
        for a in 0..2 {
            lo[a] = lo[a].min(c[a] - reach);
            hi[a] = hi[a].max(c[a] + reach);
        }
    }
    let extent = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-6);
    let scale = size as f32 * (1.0 - 2.0 * MARGIN) / extent;
    let centre = [(lo[0] + hi[0]) * 0.5, (lo[1] + hi[1]) * 0.5];
    let half = size as f32 * 0.5;
    let to_pixels = |p: Vec3| [(p[0] - centre[0]) * scale + half, half - (p[1] - centre[1]) * scale, p[2]];

    let mut depth = vec![f32::NEG_INFINITY; (size * size) as usize];
    let last = size as i64 - 1;
    for s in &splats {
        // Two-sided: a scan's normal may point away from a surface the camera sees.
        let mut n = s.normal;
        if !n.iter().all(|x| x.is_finite()) {
            n = view.to_camera;
        } else if dot(n, view.to_camera) < 0.0 {
            n = n.map(|x| -x);
        }
        let light = 0.25 + 0.75 * dot(n, view.light).max(0.0);
        let shade = s.colour.map(|c| (c * light.clamp(0.3, 1.0)).max(0.2));
        let pixel = shade.map(|c| (c * 255.0).round().clamp(0.0, 255.0) as u8);
        for face in Face::ALL {
            let axis = face.axis();
            let outward = face.sign() as f32;
            if s.faces & face.bit() == 0 || view.to_camera[axis] * outward <= 0.0 {
                continue;
            }
            let (ea, eb) = ((axis + 1) % 3, (axis + 2) % 3);
            let mut p0 = s.corner;
            if outward > 0.0 {
                p0[axis] += s.size;
            }
            let mut pa = p0;
            pa[ea] += s.size;
            let mut pb = p0;
            pb[eb] += s.size;
            let (q0, qa, qb) =
                (to_pixels(view.project(p0)), to_pixels(view.project(pa)), to_pixels(view.project(pb)));
            let a = [qa[0] - q0[0], qa[1] - q0[1], qa[2] - q0[2]];
            let b = [qb[0] - q0[0], qb[1] - q0[1], qb[2] - q0[2]];
            let det = a[0] * b[1] - a[1] * b[0];
            if det.abs() < 1e-9 {
                continue; // seen edge-on
            }
            let xs = [q0[0], q0[0] + a[0], q0[0] + b[0], q0[0] + a[0] + b[0]];
            let ys = [q0[1], q0[1] + a[1], q0[1] + b[1], q0[1] + a[1] + b[1]];
            let min = |v: [f32; 4]| v.iter().copied().fold(f32::INFINITY, f32::min);
            let max = |v: [f32; 4]| v.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let (x0, x1) = ((min(xs) - 0.5).floor() as i64, (max(xs) - 0.5).ceil() as i64);
            let (y0, y1) = ((min(ys) - 0.5).floor() as i64, (max(ys) - 0.5).ceil() as i64);
            // A sliver more than the face, so faces that share an edge leave no crack.
            const EPS: f32 = 1e-3;
            for y in y0.max(0)..=y1.min(last) {
                for x in x0.max(0)..=x1.min(last) {
                    let d = [x as f32 + 0.5 - q0[0], y as f32 + 0.5 - q0[1]];
                    let u = (d[0] * b[1] - d[1] * b[0]) / det;
                    let v = (a[0] * d[1] - a[1] * d[0]) / det;
                    if !(-EPS..=1.0 + EPS).contains(&u) || !(-EPS..=1.0 + EPS).contains(&v) {
                        continue;
                    }
                    let z = q0[2] + u * a[2] + v * b[2];
                    let i = (y * size as i64 + x) as usize;
                    if z > depth[i] {
                        depth[i] = z;
                        rgb[3 * i..3 * i + 3].copy_from_slice(&pixel);
                    }
                }
            }
        }
    }
    Image { width: size, height: size, rgb }
}

pub fn encode_png(image: &Image) -> Vec<u8> {
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, image.width, image.height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().expect("PNG header into memory");
    writer.write_image_data(&image.rgb).expect("PNG data into memory");
    writer.finish().expect("PNG end into memory");
    out
}

/// The scene's thumbnail as PNG bytes, from the level chosen by [`thumbnail_level`].
pub fn render_scene(scene: &StoredScene) -> Result<Vec<u8>, ThumbnailError> {
    let blocks = read_level(scene, thumbnail_level(&scene.manifest, MAX_VOXELS))?;
    if blocks.iter().all(|b| b.voxels.is_empty()) {
        return Err(ThumbnailError::Empty(scene.id.clone()));
    }
    Ok(encode_png(&render(&blocks, SIZE)))
}

/// Names the picture of this manifest drawn by this renderer.
pub fn cache_key(scene: &LoadedScene) -> String {
    let mut h = blake3::Hasher::new();
    h.update(RENDER_VERSION.as_bytes());
    h.update(&scene.manifest_json);
    h.finalize().to_hex()[..16].to_string()
}

/// Where the PNG is cached: beside the manifest of a local scene; a bucket scene's is rendered per
/// request (a replica does not write to the bucket).
pub fn cache_path(scene: &LoadedScene) -> Option<PathBuf> {
    Some(scene.stored.local_dir()?.join(format!("thumbnail-{}.png", cache_key(scene))))
}

/// Writes `bytes` to `path` through a uniquely named temp file and a rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension(format!("png.tmp-{:016x}", rand::random::<u64>()));
    let result = std::fs::write(&tmp, bytes).and_then(|()| std::fs::rename(&tmp, path));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// The cached PNG, or a fresh render that is cached when the store is writable.
pub fn thumbnail_png(scene: &LoadedScene) -> Result<Vec<u8>, ThumbnailError> {
    let path = cache_path(scene);
    if let Some(bytes) = path.as_ref().and_then(|p| std::fs::read(p).ok()) {
        return Ok(bytes);
    }
    let png = render_scene(&scene.stored)?;
    if let Some(path) = path
        && let Err(e) = write_atomic(&path, &png)
    {
        tracing::debug!(path = %path.display(), error = %e, "thumbnail not cached");
    }
    Ok(png)
}

#[utoipa::path(get, path = "/api/scenes/{id}/thumbnail.png", tag = "scenes",
    params(("id" = String, Path)),
    responses((status = 200, description = "A 256×256 PNG of the scene from a fixed three-quarter view", content_type = "image/png"),
        (status = 304), (status = 400), (status = 404)))]
pub async fn get_thumbnail(
    _read: ReadAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    validate_id(&id).map_err(|e| ApiError::bad_request(e.to_string()))?;
    let scene = state
        .catalog
        .find(&id)
        .await
        .ok_or_else(|| ApiError::not_found(format!("no scene with id {id:?}")))?;
    let etag = HeaderValue::from_str(&format!("\"{}\"", cache_key(&scene))).expect("hex");
    let cache = HeaderValue::from_static("no-cache");
    if headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .any(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"))
    {
        return Ok((StatusCode::NOT_MODIFIED, [(header::ETAG, etag), (header::CACHE_CONTROL, cache)])
            .into_response());
    }
    // A scene listed from its manifest reads the pages down to the thumbnail's level first.
    let level = thumbnail_level(&scene.stored.manifest, MAX_VOXELS);
    scene.stored.load_down_to(level).await.map_err(|e| {
        tracing::error!(error = %e, "thumbnail failed");
        state.read_failed(
            &scene,
            match e {
                crate::store::StoreError::Gone { .. } => ApiError::not_found(e.to_string()),
                e => ApiError::internal(e.to_string()),
            },
        )
    })?;
    let drawn = scene.clone();
    let png = tokio::task::spawn_blocking(move || thumbnail_png(&drawn))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(|e| {
            tracing::error!(error = %e, "thumbnail failed");
            state.read_failed(
                &scene,
                match e {
                    ThumbnailError::Empty(_) => ApiError::not_found(e.to_string()),
                    ThumbnailError::Block { .. } => ApiError::internal(e.to_string()),
                },
            )
        })?;
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("image/png")),
            (header::ETAG, etag),
            (header::CACHE_CONTROL, cache),
        ],
        png,
    )
        .into_response())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{BuildOptions, build_scene};
    use crate::store::open_scene;
    use std::fmt::Write as _;

    /// A unit UV sphere scaled by `stretch` per axis, as OBJ text.
    fn ellipsoid_obj(stretch: [f64; 3]) -> String {
        let (rings, segments) = (24, 48);
        let mut obj = String::new();
        for i in 0..=rings {
            let theta = std::f64::consts::PI * i as f64 / rings as f64;
            for j in 0..segments {
                let phi = 2.0 * std::f64::consts::PI * j as f64 / segments as f64;
                let p = [theta.sin() * phi.cos(), theta.cos(), theta.sin() * phi.sin()];
                writeln!(obj, "v {} {} {}", p[0] * stretch[0], p[1] * stretch[1], p[2] * stretch[2]).unwrap();
            }
        }
        let idx = |i: usize, j: usize| i * segments + j % segments + 1;
        for i in 0..rings {
            for j in 0..segments {
                let (a, b, c, d) = (idx(i, j), idx(i, j + 1), idx(i + 1, j + 1), idx(i + 1, j));
                writeln!(obj, "f {a} {b} {c}\nf {a} {c} {d}").unwrap();
            }
        }
        obj
    }

    fn build(obj: &str, resolution: u32) -> (tempfile::TempDir, StoredScene) {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("shape.obj");
        std::fs::write(&input, obj).unwrap();
        let store = dir.path().join("store");
        let opts = BuildOptions {
            resolution: crate::pipeline::Resolution::Explicit(resolution),
            ..Default::default()
        };
        let report = build_scene(&input, &store, &opts).unwrap();
        let scene = open_scene(&store, &report.id).unwrap();
        (dir, scene)
    }

    struct Silhouette {
        pixels: usize,
        min: [u32; 2],
        max: [u32; 2],
    }

    fn silhouette(img: &Image) -> Silhouette {
        let mut s = Silhouette { pixels: 0, min: [u32::MAX; 2], max: [0; 2] };
        for y in 0..img.height {
            for x in 0..img.width {
                if img.pixel(x, y) != BACKGROUND {
                    s.pixels += 1;
                    s.min = [s.min[0].min(x), s.min[1].min(y)];
                    s.max = [s.max[0].max(x), s.max[1].max(y)];
                }
            }
        }
        s
    }

    fn decode_png(bytes: &[u8]) -> Image {
        let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        buf.truncate(info.buffer_size());
        Image { width: info.width, height: info.height, rgb: buf }
    }

    #[test]
    fn sphere_is_a_shaded_disc_lit_from_above() {
        let (_dir, scene) = build(&ellipsoid_obj([1.0; 3]), 128);
        let level = thumbnail_level(&scene.manifest, MAX_VOXELS);
        let img = decode_png(&render_scene(&scene).unwrap());
        assert_eq!((img.width, img.height), (SIZE, SIZE));
        let s = silhouette(&img);
        let (w, h) = (s.max[0] - s.min[0] + 1, s.max[1] - s.min[1] + 1);
        // The fit leaves the margin free and centres the picture.
        assert!(s.min.iter().all(|&m| m >= 8) && s.max.iter().all(|&m| m <= SIZE - 8), "touches the edge");
        let centre = [(s.min[0] + s.max[0]) as f32 / 2.0, (s.min[1] + s.max[1]) as f32 / 2.0];
        assert!(centre.iter().all(|c| (c - SIZE as f32 / 2.0).abs() < 6.0), "off centre: {centre:?}");
        // A disc: square bounding box filled to about pi/4, and large in the frame.
        assert!((w as f32 / h as f32 - 1.0).abs() < 0.08, "{w}x{h} is not round (level {level})");
        let fill = s.pixels as f32 / (w * h) as f32;
        assert!((0.74..0.84).contains(&fill), "fill {fill} of the bounding box is not a disc");
        assert!(w > SIZE * 6 / 10, "the sphere is only {w} px wide");
        // Shaded, not flat: many tones, and the top (towards the light) brighter than the bottom.
        let mut tones = std::collections::HashSet::new();
        let (mut top, mut bottom) = ((0u64, 0u64), (0u64, 0u64));
        for y in s.min[1]..=s.max[1] {
            for x in s.min[0]..=s.max[0] {
                let p = img.pixel(x, y);
                if p == BACKGROUND {
                    continue;
                }
                tones.insert(p);
                let luma = p.iter().map(|&c| c as u64).sum::<u64>();
                let half = if y < (s.min[1] + s.max[1]) / 2 { &mut top } else { &mut bottom };
                *half = (half.0 + luma, half.1 + 1);
            }
        }
        assert!(tones.len() > 30, "only {} tones: not shaded", tones.len());
        let (top, bottom) = (top.0 as f64 / top.1 as f64, bottom.0 as f64 / bottom.1 as f64);
        assert!(top > bottom * 1.1, "the lit top ({top}) is not brighter than the bottom ({bottom})");
    }

    #[test]
    fn tall_shape_is_tall_and_coarse_levels_keep_the_silhouette() {
        // +Y is up on screen: an ellipsoid three times as tall as wide stands up.
        let (_dir, scene) = build(&ellipsoid_obj([0.33, 1.0, 0.33]), 256);
        let blocks0 = read_level(&scene, 0).unwrap();
        let fine = silhouette(&render(&blocks0, SIZE));
        let (w, h) = (fine.max[0] - fine.min[0] + 1, fine.max[1] - fine.min[1] + 1);
        assert!(h as f32 > 2.2 * w as f32, "{w}x{h}: the tall shape does not stand up");
        // The next level draws the same shape, within a voxel or two of the picture.
        let blocks1 = read_level(&scene, 1).unwrap();
        let coarse = silhouette(&render(&blocks1, SIZE));
        let ratio = coarse.pixels as f32 / fine.pixels as f32;
        assert!((0.9..1.15).contains(&ratio), "level 1 covers {ratio} of level 0's silhouette");
    }

    #[test]
    fn cone_stands_on_its_base() {
        // A cone with its apex up (+Y): wide at the bottom of the picture, narrow at the top.
        let segments = 64;
        let mut obj = String::from("v 0 2 0\nv 0 0 0\n");
        for j in 0..segments {
            let phi = 2.0 * std::f64::consts::PI * j as f64 / segments as f64;
            writeln!(obj, "v {} 0 {}", phi.cos(), phi.sin()).unwrap();
        }
        for j in 0..segments {
            let (a, b) = (3 + j, 3 + (j + 1) % segments);
            writeln!(obj, "f 1 {b} {a}\nf 2 {a} {b}").unwrap();
        }
        let (_dir, scene) = build(&obj, 128);
        let img = decode_png(&render_scene(&scene).unwrap());
        let s = silhouette(&img);
        let row_width = |y: u32| (0..img.width).filter(|&x| img.pixel(x, y) != BACKGROUND).count();
        let h = s.max[1] - s.min[1];
        let (top, bottom) = (row_width(s.min[1] + h / 5), row_width(s.max[1] - h / 5));
        assert!(
            bottom > 2 * top,
            "rows near the top are {top} px wide, near the bottom {bottom}: upside down?"
        );
    }

    #[test]
    fn level_choice_respects_the_budget() {
        let (_dir, scene) = build(&ellipsoid_obj([1.0; 3]), 256);
        let m = &scene.manifest;
        let voxels = |l: u8| m.levels.iter().find(|i| i.level == l).unwrap().voxels;
        assert!(voxels(0) > 20_000, "the test needs a level 0 over the small budget");
        let level = thumbnail_level(m, 20_000);
        assert!(level > 0 && voxels(level) <= 20_000 && voxels(level - 1) > 20_000, "level {level}");
        assert_eq!(thumbnail_level(m, u64::MAX), 0);
        assert_eq!(thumbnail_level(m, 0), m.coarsest_level(), "nothing fits: the coarsest level");
    }

    #[test]
    fn damaged_block_is_an_error_naming_it() {
        let (_dir, scene) = build(&ellipsoid_obj([1.0; 3]), 64);
        let level = thumbnail_level(&scene.manifest, MAX_VOXELS);
        let entry = scene.blocks().into_iter().find(|b| b.key.level == level).unwrap().clone();
        // Overwrite the block's range of its pack.
        let range = scene.index.read().pack_range(&entry.key).expect("blocks are packed");
        let pack = scene.pack_path(&range.pack.hash);
        let mut bytes = std::fs::read(&pack).unwrap();
        bytes[range.offset as usize..range.end() as usize].fill(b'x');
        std::fs::write(&pack, bytes).unwrap();
        let err = render_scene(&scene).unwrap_err().to_string();
        assert!(err.contains(&entry.key.to_string()), "{err}");
    }

    #[tokio::test]
    async fn route_serves_caches_and_revalidates() {
        use axum::body::Body;
        use axum::http::Request;
        use tower::ServiceExt;

        let (dir, _scene) = build(&ellipsoid_obj([1.0; 3]), 64);
        let store = dir.path().join("store");
        let app = crate::http::router(AppState::load(&store, None).unwrap());
        let get = |uri: &str, etag: Option<&str>| {
            let mut req = Request::get(uri);
            if let Some(e) = etag {
                req = req.header(header::IF_NONE_MATCH, e);
            }
            app.clone().oneshot(req.body(Body::empty()).unwrap())
        };
        let resp = get("/api/scenes/shape/thumbnail.png", None).await.unwrap();
        assert_eq!(resp.status(), StatusCode::OK);
        assert_eq!(resp.headers()[header::CONTENT_TYPE], "image/png");
        let etag = resp.headers()[header::ETAG].to_str().unwrap().to_string();
        let body = axum::body::to_bytes(resp.into_body(), 1 << 22).await.unwrap();
        let img = decode_png(&body);
        assert!(silhouette(&img).pixels > 1000, "the served picture is blank");
        // Cached beside the manifest under the key the ETag names.
        let cached = store.join("shape").join(format!("thumbnail-{}.png", etag.trim_matches('"')));
        assert_eq!(std::fs::read(&cached).unwrap(), body);
        let again = get("/api/scenes/shape/thumbnail.png", Some(&etag)).await.unwrap();
        assert_eq!(again.status(), StatusCode::NOT_MODIFIED);
        assert_eq!(
            get("/api/scenes/nope/thumbnail.png", None).await.unwrap().status(),
            StatusCode::NOT_FOUND
        );
        assert_eq!(
            get("/api/scenes/No..pe/thumbnail.png", None).await.unwrap().status(),
            StatusCode::BAD_REQUEST
        );
    }

    #[test]
    fn empty_input_renders_background_only() {
        let img = render(&[], 16);
        assert!(img.rgb.chunks(3).all(|p| p == BACKGROUND));
    }
}
