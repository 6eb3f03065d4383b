//! Block codec measurements on a built scene, printed as JSON:
//! compressed size of each column, decode speed, and the same voxels
//! re-blocked into 32³ and 128³ blocks with the same codec (block-size choice,
//! ARCHITECTURE.md).
//!
//!     cargo run --release -p voxstream-format --example block_stats -- <store>/<scene-id>
//!
//! Re-blocking keeps every voxel and its attributes; faces on the new block
//! boundaries become skirts (always drawn) and faces on the old 64³ boundaries
//! that fall inside a 128³ block are hidden where the neighbour voxel exists,
//! as the LOD stage would have done.

use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use std::time::Instant;

use voxstream_format::{
    BLOCK_SIZE, Block, ColumnSizes, HEADER_LEN, Manifest, VoxelColumns, decode_block, demorton3, morton3,
};

/// A voxel in level coordinates, with its attributes.
#[derive(Clone, Copy)]
struct Voxel {
    pos: [u32; 3],
    faces: u8,
    normal: u16,
    coverage: u8,
    color: Option<[u8; 3]>,
}

fn encode_columns(c: &VoxelColumns) -> (Vec<u8>, usize) {
    let raw = c.payload();
    (lz4_flex::block::compress(&raw), raw.len())
}

struct SizeStats {
    edge: u32,
    blocks_per_level: Vec<usize>,
    bytes: usize,
    decode_seconds: f64,
    voxels: usize,
}

fn measure_block_size(levels: &[Vec<Voxel>], depth: u32) -> SizeStats {
    let edge = 1u32 << depth;
    let mut blocks_per_level = Vec::new();
    let mut encoded: Vec<(Vec<u8>, usize, usize, bool, bool)> = Vec::new();
    for (level, voxels) in levels.iter().enumerate() {
        let occupied: HashSet<[u32; 3]> = voxels.iter().map(|v| v.pos).collect();
        let mut by_block: BTreeMap<[u32; 3], Vec<(u32, Voxel)>> = BTreeMap::new();
        for v in voxels {
            let key = v.pos.map(|c| c / edge);
            let local = v.pos.map(|c| c % edge);
            let mut faces = v.faces;
            for axis in 0..3 {
                for (bit, at_edge, neighbour) in [
                    (2 * axis, local[axis] == 0, v.pos[axis].checked_sub(1)),
                    (2 * axis + 1, local[axis] == edge - 1, Some(v.pos[axis] + 1)),
                ] {
                    let mut q = v.pos;
                    let was_skirt = match neighbour {
                        Some(n) => {
                            q[axis] = n;
                            // Crossing a 64³ boundary in the stored data.
                            (v.pos[axis] / BLOCK_SIZE) != (n / BLOCK_SIZE)
                        }
                        None => true,
                    };
                    if at_edge {
                        faces |= 1 << bit;
                    } else if was_skirt && neighbour.is_some() && occupied.contains(&q) {
                        faces &= !(1 << bit);
                    }
                }
            }
            if faces == 0 {
                continue; // buried once the old boundary is gone
            }
            let m = morton3(local[0], local[1], local[2]);
            by_block.entry(key).or_default().push((m, Voxel { faces, ..*v }));
        }
        blocks_per_level.push(by_block.len());
        for (_, mut vs) in by_block {
            vs.sort_by_key(|(m, _)| *m);
            let has_color = vs.iter().any(|(_, v)| v.color.is_some());
            let c = VoxelColumns {
                depth,
                morton: vs.iter().map(|(m, _)| *m).collect(),
                faces: vs.iter().map(|(_, v)| v.faces).collect(),
                normal: vs.iter().map(|(_, v)| v.normal).collect(),
                coverage: if level == 0 { Vec::new() } else { vs.iter().map(|(_, v)| v.coverage).collect() },
                color: if has_color {
                    vs.iter().map(|(_, v)| v.color.unwrap_or([0; 3])).collect()
                } else {
                    Vec::new()
                },
                field: Vec::new(),
            };
            let (packed, raw_len) = encode_columns(&c);
            encoded.push((packed, raw_len, c.len(), level > 0, has_color));
        }
    }
    let bytes = encoded.iter().map(|e| HEADER_LEN + e.0.len()).sum();
    let voxels = encoded.iter().map(|e| e.2).sum();
    let decode_seconds = time_decode(|| {
        for (packed, raw_len, count, cov, col) in &encoded {
            let raw = lz4_flex::block::decompress(packed, *raw_len).expect("own bytes");
            let c = VoxelColumns::from_payload(depth, *count, *cov, *col, &raw).expect("own bytes");
            std::hint::black_box(c);
        }
    });
    SizeStats { edge, blocks_per_level, bytes, decode_seconds, voxels }
}

/// Best of several runs, in seconds.
fn time_decode(mut f: impl FnMut()) -> f64 {
    (0..7)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    let dir = std::env::args().nth(1).expect("usage: block_stats <store>/<scene-id>");
    let dir = Path::new(&dir);
    let manifest = Manifest::from_json(&std::fs::read(dir.join("manifest.json")).expect("manifest"))
        .expect("valid manifest");
    // Pages and blocks live in packs (a range each); scenes of older builds keep them in own files.
    let read_range = |range: &voxstream_format::PackRange| -> std::io::Result<Vec<u8>> {
        use std::os::unix::fs::FileExt;
        let pack = std::fs::File::open(dir.join(voxstream_format::hierarchy::pack_path(&range.pack.hash)))?;
        let mut bytes = vec![0u8; range.bytes as usize];
        pack.read_exact_at(&mut bytes, range.offset)?;
        Ok(bytes)
    };
    let index = voxstream_format::load_scene_index(&manifest, |r, range| match range {
        Some(range) => read_range(&range),
        None => std::fs::read(dir.join(voxstream_format::hierarchy::page_path(&r.root))),
    })
    .expect("hierarchy pages");
    let mut entries: Vec<_> = index.blocks().collect();
    entries.sort_by_key(|b| b.key);
    let files: Vec<Vec<u8>> = entries
        .iter()
        .map(|b| match index.pack_range(&b.key) {
            Some(range) => read_range(&range).expect("block in its pack"),
            None => std::fs::read(dir.join("blocks").join(format!("{}.vxb", b.key))).expect("block file"),
        })
        .collect();
    let blocks: Vec<Block> = files.iter().map(|f| decode_block(f).expect("valid block")).collect();
    let voxels: usize = blocks.iter().map(|b| b.voxels.len()).sum();
    let file_bytes: usize = files.iter().map(Vec::len).sum();

    // Column sizes, each column compressed alone.
    let mut columns = ColumnSizes::default();
    // Per level: a view that stops at coarse levels fetches their mix, not the scene's.
    let mut by_level: BTreeMap<u8, (usize, usize, usize, ColumnSizes)> = BTreeMap::new();
    let mut raw_bytes = 0;
    for (b, f) in blocks.iter().zip(&files) {
        let c = VoxelColumns::from_block(b);
        let sizes = c.column_sizes();
        columns += sizes;
        let level = by_level.entry(b.key.level).or_default();
        level.0 += 1;
        level.1 += b.voxels.len();
        level.2 += f.len();
        level.3 += sizes;
        raw_bytes += c.payload().len();
    }
    let level_rows: Vec<serde_json::Value> = by_level
        .iter()
        .map(|(level, (n, voxels, bytes, c))| {
            serde_json::json!({
                "level": level, "blocks": n, "voxels": voxels, "block_file_bytes": bytes,
                "bytes_per_voxel": *bytes as f64 / *voxels as f64,
                "occupancy": c.occupancy, "faces": c.faces, "normals": c.normals,
                "coverage": c.coverage, "colors": c.colors, "field": c.field,
            })
        })
        .collect();

    // Full decode (header checks, lz4, columns, PackedVoxel) as the viewer does it.
    let seconds = time_decode(|| {
        for f in &files {
            std::hint::black_box(decode_block(f).expect("valid"));
        }
    });

    // Voxels per level in level coordinates, for re-blocking.
    let mut levels: Vec<Vec<Voxel>> = vec![Vec::new(); manifest.levels.len()];
    for b in &blocks {
        for v in &b.voxels {
            let local = demorton3(v.morton());
            levels[b.key.level as usize].push(Voxel {
                pos: std::array::from_fn(|a| b.key.coord()[a] * BLOCK_SIZE + local[a]),
                faces: v.faces(),
                normal: v.normal as u16,
                coverage: v.coverage(),
                color: v.color(),
            });
        }
    }
    let sizes: Vec<SizeStats> = [5, 6, 7].iter().map(|&d| measure_block_size(&levels, d)).collect();

    let triangles = manifest.source.triangles as f64;
    let size_rows: Vec<serde_json::Value> = sizes
        .iter()
        .map(|s| {
            serde_json::json!({
                "block_edge": s.edge,
                "blocks_per_level": s.blocks_per_level,
                "blocks": s.blocks_per_level.iter().sum::<usize>(),
                "bytes": s.bytes,
                "bytes_per_triangle": s.bytes as f64 / triangles,
                "mean_block_bytes": s.bytes as f64 / s.blocks_per_level.iter().sum::<usize>() as f64,
                "voxels": s.voxels,
                "payload_decode_mvoxels_per_s": s.voxels as f64 / s.decode_seconds / 1e6,
            })
        })
        .collect();
    let out = serde_json::json!({
        "scene": manifest.name,
        "triangles": manifest.source.triangles,
        "blocks": blocks.len(),
        "voxels": voxels,
        "block_file_bytes": file_bytes,
        "bytes_per_triangle": file_bytes as f64 / triangles,
        "bytes_per_voxel": file_bytes as f64 / voxels as f64,
        "payload_raw_bytes": raw_bytes,
        "columns_lz4_alone": {
            "occupancy": columns.occupancy,
            "faces": columns.faces,
            "normals": columns.normals,
            "coverage": columns.coverage,
            "colors": columns.colors,
            "headers": blocks.len() * HEADER_LEN,
        },
        "columns_by_level": level_rows,
        "decode_block": {
            "seconds": seconds,
            "mvoxels_per_s": voxels as f64 / seconds / 1e6,
            "mb_per_s": file_bytes as f64 / seconds / 1e6,
        },
        "block_sizes": size_rows,
    });
    println!("{}", serde_json::to_string_pretty(&out).expect("json"));
}
