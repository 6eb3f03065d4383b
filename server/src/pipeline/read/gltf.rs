//! glTF 2.0, JSON or GLB, through the gltf crate's document model only.
//!
//! Buffers come from the GLB BIN chunk or `data:` URIs and nothing else: an
//! upload must not make us open files or the network. Accessors are read here
//! rather than with gltf's reader helpers, which assert on a short stride and
//! can overflow on hostile offsets; every bound is checked before any read.

use std::borrow::Cow;

use base64::Engine as _;
use base64::engine::{DecodePaddingMode, GeneralPurpose, GeneralPurposeConfig};
use gltf::accessor::{DataType, Dimensions};
use gltf::buffer::Source;
use gltf::mesh::Mode;
use gltf::scene::Transform;
use gltf::{Accessor, Document, Gltf, Node, Primitive, Semantic};

use super::{IngestError, MeshFormat, TriangleMesh};

/// Required extensions that change nothing about positions or indices; any
/// other (Draco, meshopt, quantization, instancing, …) is refused by name.
const GEOMETRY_NEUTRAL_PREFIXES: &[&str] =
    &["KHR_materials_", "KHR_texture_", "KHR_lights_punctual", "EXT_texture_", "MSFT_texture_dds"];

/// Column-major, as glTF stores matrices; f64 so deep hierarchies and large
/// translations (georeferenced models) lose nothing before voxelization.
type Mat4 = [[f64; 4]; 4];

const IDENTITY: Mat4 =
    [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];

/// Glb header (magic, version, length) plus the JSON chunk header.
const GLB_MIN_LEN: usize = 20;

struct Reader {
    format: MeshFormat,
}

impl Reader {
    fn parse(&self, message: impl Into<String>) -> IngestError {
        IngestError::Parse { format: self.format, message: message.into() }
    }

    fn unsupported(&self, message: impl Into<String>) -> IngestError {
        IngestError::Unsupported { format: self.format, message: message.into() }
    }
}

pub(super) fn read(bytes: &[u8]) -> Result<TriangleMesh, IngestError> {
    let glb = bytes.starts_with(b"glTF");
    let r = Reader { format: if glb { MeshFormat::Glb } else { MeshFormat::Gltf } };
    if glb {
        check_glb_header(&r, bytes)?;
    }
    let Gltf { document, blob } =
        Gltf::from_slice_without_validation(bytes).map_err(|e| r.parse(e.to_string()))?;
    // gltf refuses every required extension it was not compiled with; decide
    // here instead, so the error names the extension and material-only ones pass.
    let mut json = document.into_json();
    check_required_extensions(&r, &json.extensions_required)?;
    json.extensions_required.clear();
    validate(&r, &json)?;
    let document = Document::from_json_without_validation(json);

    let buffers = load_buffers(&r, &document, blob.as_deref())?;
    let mut mesh = TriangleMesh::default();
    for (scene, roots) in scene_roots(&document).into_iter().enumerate() {
        walk_scene(&r, &document, scene, roots, &buffers, &mut mesh)?;
    }
    Ok(mesh)
}

/// gltf's validation (index ranges, enum values) minus one rule: POSITION's
/// min/max are required by the spec but often left out, and nothing here needs them.
fn validate(r: &Reader, root: &gltf::json::Root) -> Result<(), IngestError> {
    use gltf::json::validation::{Error, Validate};
    let tolerated = |path: &str, e: &Error| {
        matches!(e, Error::Missing)
            && (path.ends_with(r#".attributes["POSITION"].min"#)
                || path.ends_with(r#".attributes["POSITION"].max"#))
    };
    // gltf-json's POSITION hook indexes `accessors` before checking the index, so check first.
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            if let Some(bad) = prim.attributes.values().find(|a| a.value() >= root.accessors.len()) {
                return Err(r.parse(format!(
                    "invalid glTF: meshes[{m}].primitives[{p}] uses accessor {}, but the file has {}",
                    bad.value(),
                    root.accessors.len()
                )));
            }
        }
    }
    let mut errors = Vec::new();
    root.validate(root, gltf::json::Path::new, &mut |path, e| {
        let path = path().to_string();
        if !tolerated(&path, &e) {
            errors.push(format!("{path}: {e}"));
        }
    });
    match errors.is_empty() {
        true => Ok(()),
        false => Err(r.parse(format!("invalid glTF: {}", errors.join("; ")))),
    }
}

/// gltf computes `length - 12` unchecked, which panics on a short length under overflow checks.
fn check_glb_header(r: &Reader, bytes: &[u8]) -> Result<(), IngestError> {
    if bytes.len() < GLB_MIN_LEN {
        return Err(
            r.parse(format!("the file has {} bytes, a GLB needs at least {GLB_MIN_LEN}", bytes.len()))
        );
    }
    let declared = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
    if declared < GLB_MIN_LEN || declared > bytes.len() {
        return Err(
            r.parse(format!("the GLB header declares {declared} bytes, but the file has {}", bytes.len()))
        );
    }
    Ok(())
}

fn check_required_extensions(r: &Reader, required: &[String]) -> Result<(), IngestError> {
    match required.iter().find(|e| !GEOMETRY_NEUTRAL_PREFIXES.iter().any(|p| e.starts_with(p))) {
        Some(ext) => Err(r.unsupported(format!(
            "the file requires the glTF extension {ext}, which voxstream cannot read \
             (re-export without geometry compression or quantization)"
        ))),
        None => Ok(()),
    }
}

/// Every buffer's bytes: the GLB BIN chunk or a base64 `data:` URI. Any other URI is refused.
fn load_buffers<'a>(
    r: &Reader,
    document: &Document,
    blob: Option<&'a [u8]>,
) -> Result<Vec<Cow<'a, [u8]>>, IngestError> {
    document
        .buffers()
        .map(|buffer| match buffer.source() {
            Source::Bin => blob.map(Cow::Borrowed).ok_or_else(|| {
                r.parse(format!("buffer {} refers to the GLB BIN chunk, but there is none", buffer.index()))
            }),
            Source::Uri(uri) => decode_data_uri(uri).map(Cow::Owned).map_err(|why| {
                r.unsupported(format!("buffer {} has the URI {:?}: {why}", buffer.index(), truncate(uri)))
            }),
        })
        .collect()
}

fn decode_data_uri(uri: &str) -> Result<Vec<u8>, String> {
    let Some(rest) = uri.strip_prefix("data:") else {
        return Err("only embedded data (the GLB BIN chunk or base64 data: URIs) is read, \
                    never files or the network"
            .into());
    };
    let Some((media, payload)) = rest.split_once(',') else {
        return Err("a data: URI without a comma".into());
    };
    if !media.ends_with(";base64") {
        return Err("only base64 data: URIs are supported".into());
    }
    // Some exporters drop the trailing '=' padding; the bytes are the same.
    let engine = GeneralPurpose::new(
        &base64::alphabet::STANDARD,
        GeneralPurposeConfig::new().with_decode_padding_mode(DecodePaddingMode::Indifferent),
    );
    engine.decode(payload).map_err(|e| format!("bad base64: {e}"))
}

/// Long data URIs would drown the message; the scheme and start are enough to find it.
fn truncate(s: &str) -> Cow<'_, str> {
    const MAX: usize = 80;
    match s.char_indices().nth(MAX) {
        Some((i, _)) => Cow::Owned(format!("{}…", &s[..i])),
        None => Cow::Borrowed(s),
    }
}

/// The default scene, else every scene, else (no scenes at all) every node no other node lists as a child.
fn scene_roots(document: &Document) -> Vec<Vec<Node<'_>>> {
    if let Some(scene) = document.default_scene() {
        return vec![scene.nodes().collect()];
    }
    if document.scenes().len() > 0 {
        return document.scenes().map(|s| s.nodes().collect()).collect();
    }
    let mut is_child = vec![false; document.nodes().len()];
    for child in document.nodes().flat_map(|n| n.children()) {
        is_child[child.index()] = true;
    }
    vec![document.nodes().filter(|n| !is_child[n.index()]).collect()]
}

/// Depth-first with an explicit stack; a node met twice (a cycle, or shared
/// between parents) is an error rather than endless recursion.
fn walk_scene(
    r: &Reader,
    document: &Document,
    scene: usize,
    roots: Vec<Node<'_>>,
    buffers: &[Cow<'_, [u8]>],
    mesh: &mut TriangleMesh,
) -> Result<(), IngestError> {
    let mut seen = vec![false; document.nodes().len()];
    let mut stack: Vec<(Node, Mat4)> = roots.into_iter().rev().map(|n| (n, IDENTITY)).collect();
    while let Some((node, parent)) = stack.pop() {
        if std::mem::replace(&mut seen[node.index()], true) {
            return Err(r.parse(format!(
                "node {} is reached twice in scene {scene}: the node hierarchy must be a tree",
                node.index()
            )));
        }
        let world = mul(&parent, &local_matrix(node.transform()));
        if let Some(m) = node.mesh() {
            for primitive in m.primitives() {
                push_primitive(r, &primitive, m.index(), &world, buffers, mesh)?;
            }
        }
        stack.extend(node.children().collect::<Vec<_>>().into_iter().rev().map(|c| (c, world)));
    }
    Ok(())
}

fn push_primitive(
    r: &Reader,
    primitive: &Primitive<'_>,
    mesh_index: usize,
    world: &Mat4,
    buffers: &[Cow<'_, [u8]>],
    mesh: &mut TriangleMesh,
) -> Result<(), IngestError> {
    let what = format!("mesh {mesh_index} primitive {}", primitive.index());
    let mode = primitive.mode();
    if !matches!(mode, Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan) {
        return Ok(()); // points and lines have no surface to voxelize
    }
    // A primitive without POSITION is not drawn (glTF 2.0 §3.7.2.1).
    let Some(positions) = primitive.get(&Semantic::Positions) else { return Ok(()) };
    if positions.dimensions() != Dimensions::Vec3 || positions.data_type() != DataType::F32 {
        return Err(r.unsupported(format!(
            "{what}: POSITION is {:?} of {:?}; only VEC3 of FLOAT is supported",
            positions.dimensions(),
            positions.data_type()
        )));
    }
    let vertices = elements(r, &positions, buffers)?;
    let base = mesh.positions.len();
    let total = base as u64 + vertices.count as u64;
    if total > u64::from(u32::MAX) + 1 {
        return Err(IngestError::Invalid(format!("{total} vertices do not fit 32-bit indices")));
    }
    let indices = match primitive.indices() {
        Some(acc) => read_indices(r, &acc, buffers, &what)?,
        None => (0..vertices.count as u32).collect(),
    };
    if let Some((k, &bad)) = indices.iter().enumerate().find(|&(_, &i)| i as usize >= vertices.count) {
        return Err(r.parse(format!(
            "{what}: index {k} is {bad}, but POSITION has only {} vertices",
            vertices.count
        )));
    }
    let triangles = assemble(mode, &indices)
        .ok_or_else(|| r.parse(format!("{what}: {} indices do not make whole triangles", indices.len())))?;

    mesh.positions.extend(vertices.iter().map(|e| transform_point(world, read_vec3(e))));
    // A mirroring transform flips the winding; keep faces pointing outwards.
    let mirrored = det3(world) < 0.0;
    let base = base as u32;
    mesh.triangles.extend(triangles.map(|[a, b, c]| {
        let [a, b, c] = [a + base, b + base, c + base];
        if mirrored { [a, c, b] } else { [a, b, c] }
    }));
    Ok(())
}

/// Triangles from an index list by topology (glTF 2.0 §3.7.2.1); `None` when TRIANGLES leaves a remainder.
fn assemble(mode: Mode, idx: &[u32]) -> Option<Box<dyn Iterator<Item = [u32; 3]> + '_>> {
    let strip_len = idx.len().saturating_sub(2);
    Some(match mode {
        Mode::Triangles if idx.len().is_multiple_of(3) => {
            Box::new(idx.chunks_exact(3).map(|t| [t[0], t[1], t[2]]))
        }
        Mode::TriangleStrip => {
            Box::new((0..strip_len).map(|i| [idx[i], idx[i + 1 + i % 2], idx[i + 2 - i % 2]]))
        }
        Mode::TriangleFan => Box::new((0..strip_len).map(|i| [idx[i + 1], idx[i + 2], idx[0]])),
        _ => return None,
    })
}

fn read_indices(
    r: &Reader,
    acc: &Accessor<'_>,
    buffers: &[Cow<'_, [u8]>],
    what: &str,
) -> Result<Vec<u32>, IngestError> {
    if acc.dimensions() != Dimensions::Scalar {
        return Err(r.parse(format!("{what}: indices are {:?}, not SCALAR", acc.dimensions())));
    }
    let e = elements(r, acc, buffers)?;
    Ok(match acc.data_type() {
        DataType::U8 => e.iter().map(|b| u32::from(b[0])).collect(),
        DataType::U16 => e.iter().map(|b| u32::from(u16::from_le_bytes([b[0], b[1]]))).collect(),
        DataType::U32 => e.iter().map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
        other => return Err(r.parse(format!("{what}: indices of {other:?}; glTF allows u8, u16 or u32"))),
    })
}

/// One accessor's elements as byte slices. Every bound is checked here, so reading an element cannot panic.
struct Elements<'a> {
    data: &'a [u8],
    stride: usize,
    size: usize,
    count: usize,
}

impl<'a> Elements<'a> {
    fn iter(&self) -> impl Iterator<Item = &'a [u8]> + '_ {
        (0..self.count).map(|i| &self.data[i * self.stride..i * self.stride + self.size])
    }
}

fn elements<'a>(
    r: &Reader,
    acc: &Accessor<'_>,
    buffers: &'a [Cow<'_, [u8]>],
) -> Result<Elements<'a>, IngestError> {
    let a = acc.index();
    if acc.sparse().is_some() {
        return Err(r.unsupported(format!("accessor {a} is sparse; sparse accessors are not supported")));
    }
    let Some(view) = acc.view() else {
        return Err(r.unsupported(format!("accessor {a} has no bufferView (implicit zeros)")));
    };
    let (v, size, count) = (view.index(), acc.size(), acc.count());
    let stride = view.stride().unwrap_or(size);
    if stride < size {
        return Err(r.parse(format!(
            "bufferView {v} has stride {stride}, less than accessor {a}'s {size}-byte elements"
        )));
    }
    let b = view.buffer().index();
    let buffer: &[u8] = buffers.get(b).map_or(&[], |c| c);
    let view_bytes = view.offset().checked_add(view.length()).and_then(|end| buffer.get(view.offset()..end));
    let Some(view_bytes) = view_bytes else {
        return Err(r.parse(format!(
            "bufferView {v} (offset {}, length {}) lies outside buffer {b} ({} bytes)",
            view.offset(),
            view.length(),
            buffer.len()
        )));
    };
    let span = match count {
        0 => Some(0),
        n => (n - 1).checked_mul(stride).and_then(|s| s.checked_add(size)),
    };
    let data =
        span.and_then(|s| acc.offset().checked_add(s)).and_then(|end| view_bytes.get(acc.offset()..end));
    let Some(data) = data else {
        return Err(r.parse(format!(
            "accessor {a} (offset {}, {count} elements of {size} bytes, stride {stride}) runs past \
             bufferView {v} ({} bytes)",
            acc.offset(),
            view_bytes.len()
        )));
    };
    Ok(Elements { data, stride, size, count })
}

fn read_vec3(b: &[u8]) -> [f64; 3] {
    let f = |i: usize| f64::from(f32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]));
    [f(0), f(4), f(8)]
}

fn local_matrix(t: Transform) -> Mat4 {
    match t {
        Transform::Matrix { matrix } => matrix.map(|c| c.map(f64::from)),
        Transform::Decomposed { translation, rotation, scale } => {
            let [x, y, z, w] = rotation.map(f64::from);
            // Normalized in f64: exporters write f32 quaternions a few ulps off unit length.
            let n = (x * x + y * y + z * z + w * w).sqrt();
            let [x, y, z, w] = if n > 0.0 { [x / n, y / n, z / n, w / n] } else { [0.0, 0.0, 0.0, 1.0] };
            let rot = [
                [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + z * w), 2.0 * (x * z - y * w)],
                [2.0 * (x * y - z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + x * w)],
                [2.0 * (x * z + y * w), 2.0 * (y * z - x * w), 1.0 - 2.0 * (x * x + y * y)],
            ];
            let s = scale.map(f64::from);
            let col = |c: usize| [rot[c][0] * s[c], rot[c][1] * s[c], rot[c][2] * s[c], 0.0];
            let t = translation.map(f64::from);
            [col(0), col(1), col(2), [t[0], t[1], t[2], 1.0]]
        }
    }
}

fn mul(a: &Mat4, b: &Mat4) -> Mat4 {
    std::array::from_fn(|c| std::array::from_fn(|row| (0..4).map(|k| a[k][row] * b[c][k]).sum()))
}

/// Node matrices are affine in glTF, so the bottom row is ignored.
fn transform_point(m: &Mat4, p: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|row| m[0][row] * p[0] + m[1][row] * p[1] + m[2][row] * p[2] + m[3][row])
}

fn det3(m: &Mat4) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[2][1] * m[1][2]) - m[1][0] * (m[0][1] * m[2][2] - m[2][1] * m[0][2])
        + m[2][0] * (m[0][1] * m[1][2] - m[1][1] * m[0][2])
}

#[cfg(test)]
mod tests {
    use serde_json::{Value, json};

    use super::*;

    const SQUARE: [[f32; 3]; 4] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]];

    enum Indices {
        None,
        U8(Vec<u8>),
        U16(Vec<u16>),
        U32(Vec<u32>),
    }

    /// One mesh with one primitive: POSITION at bufferView 0, indices (if any) at bufferView 1.
    fn document(positions: &[[f32; 3]], indices: Indices, mode: u32, nodes: Value) -> (Value, Vec<u8>) {
        let mut bin: Vec<u8> = positions.as_flattened().iter().flat_map(|c| c.to_le_bytes()).collect();
        let pos_len = bin.len();
        let (ctype, count, idx): (u32, usize, Vec<u8>) = match indices {
            Indices::None => (0, 0, vec![]),
            Indices::U8(v) => (5121, v.len(), v),
            Indices::U16(v) => (5123, v.len(), v.iter().flat_map(|i| i.to_le_bytes()).collect()),
            Indices::U32(v) => (5125, v.len(), v.iter().flat_map(|i| i.to_le_bytes()).collect()),
        };
        bin.extend_from_slice(&idx);
        let mut primitive = json!({"attributes": {"POSITION": 0}, "mode": mode});
        let mut views = vec![json!({"buffer": 0, "byteOffset": 0, "byteLength": pos_len})];
        // f32::min/max skip NaN, so the bounds stay valid JSON numbers.
        let bound = |f: fn(f32, f32) -> f32, init: f32| -> Vec<f32> {
            (0..3).map(|c| positions.iter().fold(init, |m, p| f(m, p[c]))).collect()
        };
        let (min, max) = (bound(f32::min, f32::MAX), bound(f32::max, f32::MIN));
        let mut accessors = vec![json!({"bufferView": 0, "componentType": 5126, "count": positions.len(),
            "type": "VEC3", "min": min, "max": max})];
        if ctype != 0 {
            primitive["indices"] = json!(1);
            views.push(json!({"buffer": 0, "byteOffset": pos_len, "byteLength": idx.len()}));
            accessors
                .push(json!({"bufferView": 1, "componentType": ctype, "count": count, "type": "SCALAR"}));
        }
        let json = json!({
            "asset": {"version": "2.0"},
            "scene": 0,
            "scenes": [{"nodes": [0]}],
            "nodes": nodes,
            "meshes": [{"primitives": [primitive]}],
            "accessors": accessors,
            "bufferViews": views,
            "buffers": [{"byteLength": bin.len()}],
        });
        (json, bin)
    }

    fn glb(json: &Value, bin: &[u8]) -> Vec<u8> {
        let pad = |mut v: Vec<u8>, fill: u8| {
            v.resize(v.len().next_multiple_of(4), fill);
            v
        };
        let json = pad(serde_json::to_vec(json).unwrap(), b' ');
        let bin = pad(bin.to_vec(), 0);
        let total = 12 + 8 + json.len() + 8 + bin.len();
        let mut out = b"glTF".to_vec();
        for word in [2, total as u32, json.len() as u32, 0x4E4F_534A] {
            out.extend_from_slice(&u32::to_le_bytes(word));
        }
        out.extend_from_slice(&json);
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(&0x004E_4942u32.to_le_bytes());
        out.extend_from_slice(&bin);
        out
    }

    fn single_node() -> Value {
        json!([{"mesh": 0}])
    }

    fn err(bytes: &[u8]) -> String {
        read(bytes).unwrap_err().to_string()
    }

    #[test]
    fn glb_node_transforms_apply_parent_then_child() {
        // Parent translates by (10, 0, 0); child scales by 2 and turns 90° about z.
        let h = std::f32::consts::FRAC_1_SQRT_2;
        let nodes = json!([
            {"translation": [10.0, 0.0, 0.0], "children": [1]},
            {"mesh": 0, "scale": [2.0, 2.0, 2.0], "rotation": [0.0, 0.0, h, h]},
        ]);
        let (json, bin) = document(&SQUARE, Indices::U16(vec![0, 1, 2, 0, 2, 3]), 4, nodes);
        let m = read(&glb(&json, &bin)).unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        let expect = [[10.0, 0.0, 0.0], [10.0, 2.0, 0.0], [8.0, 2.0, 0.0], [8.0, 0.0, 0.0]];
        for (got, want) in m.positions.iter().zip(expect) {
            assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-6), "{got:?} vs {want:?}");
        }
    }

    #[test]
    fn missing_position_bounds_are_tolerated_other_validation_is_not() {
        let (mut json, bin) = document(&SQUARE[..3], Indices::None, 4, single_node());
        json["accessors"][0].as_object_mut().unwrap().retain(|k, _| k != "min" && k != "max");
        assert_eq!(read(&glb(&json, &bin)).unwrap().triangles.len(), 1);
        json["accessors"][0]["componentType"] = json!(1234);
        let e = err(&glb(&json, &bin));
        assert!(e.contains("accessors[0].componentType"), "{e}");
    }

    #[test]
    fn matrix_transform_and_u32_u8_indices() {
        let nodes = json!([{"mesh": 0, "matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 5,6,7,1]}]);
        for indices in [Indices::U32(vec![0, 1, 2, 0, 2, 3]), Indices::U8(vec![0, 1, 2, 0, 2, 3])] {
            let (json, bin) = document(&SQUARE, indices, 4, nodes.clone());
            let m = read(&glb(&json, &bin)).unwrap();
            assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
            assert_eq!(m.positions[2], [6.0, 7.0, 7.0]);
        }
    }

    #[test]
    fn mirroring_transform_flips_winding() {
        let nodes = json!([{"mesh": 0, "scale": [-1.0, 1.0, 1.0]}]);
        let (json, bin) = document(&SQUARE[..3], Indices::None, 4, nodes);
        let m = read(&glb(&json, &bin)).unwrap();
        assert_eq!(m.triangles, vec![[0, 2, 1]]);
        assert_eq!(m.positions[1], [-1.0, 0.0, 0.0]);
    }

    #[test]
    fn strips_and_fans_follow_the_spec_and_lines_are_skipped() {
        let (json, bin) = document(&SQUARE, Indices::None, 5, single_node());
        assert_eq!(read(&glb(&json, &bin)).unwrap().triangles, vec![[0, 1, 2], [1, 3, 2]]);
        let (json, bin) = document(&SQUARE, Indices::None, 6, single_node());
        assert_eq!(read(&glb(&json, &bin)).unwrap().triangles, vec![[1, 2, 0], [2, 3, 0]]);
        let (json, bin) = document(&SQUARE, Indices::None, 1, single_node());
        assert!(read(&glb(&json, &bin)).unwrap().triangles.is_empty());
    }

    #[test]
    fn gltf_with_base64_data_uri() {
        let (mut json, bin) = document(&SQUARE, Indices::U16(vec![0, 1, 2]), 4, single_node());
        let b64 = base64::engine::general_purpose::STANDARD.encode(&bin);
        json["buffers"][0]["uri"] = json!(format!("data:application/octet-stream;base64,{b64}"));
        let m = read(&serde_json::to_vec(&json).unwrap()).unwrap();
        assert_eq!(m.positions[..3], SQUARE[..3].iter().map(|p| p.map(f64::from)).collect::<Vec<_>>()[..]);
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
        // Unpadded base64 is the same data.
        json["buffers"][0]["uri"] = json!(format!("data:;base64,{}", b64.trim_end_matches('=')));
        assert_eq!(read(&serde_json::to_vec(&json).unwrap()).unwrap(), m);
    }

    #[test]
    fn file_and_network_uris_are_refused_by_name() {
        for uri in ["scene.bin", "../../etc/passwd", "file:///etc/passwd", "https://example.com/a.bin"] {
            let (mut json, _) = document(&SQUARE[..3], Indices::None, 4, single_node());
            json["buffers"][0]["uri"] = json!(uri);
            let e = err(&serde_json::to_vec(&json).unwrap());
            assert!(e.contains(uri) && e.contains("never files"), "{e}");
        }
    }

    #[test]
    fn compression_extensions_are_refused_by_name() {
        for ext in ["KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_mesh_quantization"] {
            let (mut json, bin) = document(&SQUARE[..3], Indices::None, 4, single_node());
            json["extensionsUsed"] = json!([ext]);
            json["extensionsRequired"] = json!(["KHR_materials_unlit", ext]);
            let e = err(&glb(&json, &bin));
            assert!(e.contains(ext) && e.starts_with("unsupported glb"), "{e}");
        }
        // Material-only required extensions do not stop the geometry.
        let (mut json, bin) = document(&SQUARE[..3], Indices::None, 4, single_node());
        json["extensionsRequired"] = json!(["KHR_materials_unlit", "KHR_texture_transform"]);
        assert_eq!(read(&glb(&json, &bin)).unwrap().triangles.len(), 1);
    }

    #[test]
    fn truncated_glb_is_an_error_at_every_length() {
        let (json, bin) = document(&SQUARE, Indices::U16(vec![0, 1, 2, 0, 2, 3]), 4, single_node());
        let full = glb(&json, &bin);
        for len in 0..full.len() {
            assert!(read(&full[..len]).is_err(), "{len}");
        }
        // A header length below the header itself (gltf would underflow on it).
        let mut short = full.clone();
        short[8..12].copy_from_slice(&4u32.to_le_bytes());
        assert!(err(&short).contains("declares 4 bytes"));
    }

    #[test]
    fn out_of_bounds_accessors_and_views_are_errors() {
        let cases = [
            ("accessors", "count", json!(5), "accessor 0 (offset 0, 5 elements"),
            ("accessors", "byteOffset", json!(4), "accessor 0 (offset 4"),
            ("accessors", "byteOffset", json!(u64::MAX / 2), "accessor 0"),
            ("bufferViews", "byteLength", json!(4096), "lies outside buffer 0"),
            ("bufferViews", "byteOffset", json!(u64::MAX - 4), "lies outside buffer 0"),
            ("bufferViews", "byteStride", json!(8), "stride 8, less than"),
        ];
        for (array, key, value, expect) in cases {
            let (mut json, bin) = document(&SQUARE, Indices::U16(vec![0, 1, 2]), 4, single_node());
            json[array][0][key] = value;
            let e = err(&glb(&json, &bin));
            assert!(e.contains(expect), "{array}.{key}: {e}");
        }
    }

    #[test]
    fn bad_indices_and_graphs_are_errors() {
        let (json, bin) = document(&SQUARE, Indices::U16(vec![0, 1, 4]), 4, single_node());
        assert!(err(&glb(&json, &bin)).contains("index 2 is 4"));
        let (json, bin) = document(&SQUARE, Indices::U16(vec![0, 1, 2, 3]), 4, single_node());
        assert!(err(&glb(&json, &bin)).contains("whole triangles"));
        let (json, bin) = document(
            &SQUARE[..3],
            Indices::None,
            4,
            json!([{"mesh": 0, "children": [1]}, {"children": [0]}]),
        );
        let e = err(&glb(&json, &bin));
        assert!(e.contains("reached twice"), "{e}");
        let (json, bin) = document(&SQUARE[..3], Indices::None, 4, json!([{"mesh": 0, "children": [7]}]));
        assert!(err(&glb(&json, &bin)).starts_with("not a valid glb"));
    }

    #[test]
    fn nan_positions_pass_through() {
        let nan = [[f32::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let (json, bin) = document(&nan, Indices::None, 4, single_node());
        let m = read(&glb(&json, &bin)).unwrap();
        assert!(m.positions[0][0].is_nan());
        assert_eq!(m.positions[2], [0.0, 1.0, 0.0]);
    }

    #[test]
    fn no_default_scene_reads_every_scene() {
        let (mut json, bin) = document(
            &SQUARE[..3],
            Indices::None,
            4,
            json!([{"mesh": 0}, {"mesh": 0, "translation": [0, 0, 3]}]),
        );
        json.as_object_mut().unwrap().remove("scene");
        json["scenes"] = json!([{"nodes": [0]}, {"nodes": [1]}]);
        let m = read(&glb(&json, &bin)).unwrap();
        assert_eq!(m.triangles.len(), 2);
        assert_eq!(m.positions[3], [0.0, 0.0, 3.0]);
    }
}
