//! Write: packs finished blocks, encodes them, writes them and the hierarchy
//! pages into a scene directory and publishes it atomically.
//!
//! Layout: `<store>/<id>/manifest.json` and `<store>/<id>/packs/<blake3>.vxp`:
//! the encoded bytes of blocks, and the hierarchy pages, concatenated in the
//! order they were finished (the pyramid's post order), a pack closing at
//! [`PACK_MAX_ITEMS`] items or [`PACK_MAX_BYTES`], so one pack spans several
//! pages; the root block and the root page go last. The one open pack is a
//! temporary file (blake3 hashed as it grows), synced once and renamed to its
//! content address when it closes. A page names its blocks' packs and its
//! child pages' pack ranges, so it is sealed and appended once its root block
//! came and every pack it names is closed (until then the [`PageBuilder`]
//! holds it). A scene is written under `<store>/.tmp-<id>-<pid>-<n>` and
//! renamed into place only once every file is written and synced, so readers
//! never see a half-written scene. Directories starting with `.` are never
//! listed.
//!
//! Durability is batched: block bytes are appended to packs and pages written
//! without a sync each, and [`sync_tree`] makes the whole temporary directory
//! durable once, after the manifest and before the publishing rename. Nothing
//! is visible before that rename, so a crash before it leaves only a `.tmp-*`
//! directory that start-up cleanup removes.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use voxstream_format::hierarchy::pack_path;
use voxstream_format::{
    BLOCK_DEPTH, BLOCK_SIZE, Block, BlockEntry, BlockKey, BlockLocation, FORMAT_VERSION, GridFrame,
    LevelInfo, Manifest, PAGE_LEVELS, PackRef, PackedVoxel, PageBuilder, PageError, ResolutionChoice,
    SourceInfo, VoxelBounds, VoxelColumns, coverage_from_count, demorton3, encode_columns, morton3,
    oct_encode, oct_encode_many,
};

use crate::pipeline::aofield::AoField;
use crate::pipeline::progress::{ProgressSink, Stage, StageCounter};
use crate::pipeline::pyramid::{DrawnBlock, LodBlock, block_morton, level_count, local_position};
use crate::store::{StoreError, io, validate_id};

/// Linear [0, 1] → sRGB8 (the viewer shows colours as stored, like its grey).
pub fn linear_to_srgb8(c: f32) -> u8 {
    let c = if c.is_finite() { c.clamp(0.0, 1.0) } else { 0.0 };
    let s = if c <= 0.003_130_8 { 12.92 * c } else { 1.055 * c.powf(1.0 / 2.4) - 0.055 };
    (s * 255.0).round() as u8
}

/// Average colour of a voxel as sRGB8, if it has any colour weight.
fn average_color(v: &voxstream_format::PackedVoxel, sum: [f32; 3], weight: f32) -> PackedVoxel {
    if weight > 0.0 && weight.is_finite() {
        v.with_color(sum.map(|c| linear_to_srgb8(c / weight)))
    } else {
        *v
    }
}

/// Neutral colour for uncoloured voxels in a block that has colour (the
/// viewer's grey, BASE_COLOUR in shaders/voxel.wgsl).
pub const NEUTRAL_SRGB8: [u8; 3] = [219, 204, 184];

/// The block as stored: normals are the normalised sums (octahedral snorm8),
/// colours the area-weighted averages (sRGB8; blocks with no colour weight at
/// all have no colour column), coverage the solid count over 8^level.
pub fn packed_block(b: &LodBlock) -> Block {
    let level = b.key.level;
    let has_color = b.voxels.iter().any(|v| v.voxel.color_weight > 0.0);
    Block {
        key: b.key,
        voxels: b
            .voxels
            .iter()
            .map(|v| {
                let mut p =
                    PackedVoxel::new(local_position(&v.voxel), v.voxel.faces, oct_encode(v.voxel.normal_sum))
                        .with_coverage(coverage_from_count(v.solid as u64, level));
                if has_color {
                    p = average_color(&p.with_color(NEUTRAL_SRGB8), v.voxel.color_sum, v.voxel.color_weight);
                }
                p
            })
            .collect(),
    }
}

/// The codec's columns of [`packed_block`], straight from the voxels: what
/// `VoxelColumns::from_block(&packed_block(b))` gives (tested), without the
/// packed form's Morton → position → Morton round trip.
fn block_columns(b: &LodBlock, field: Option<&AoField>) -> VoxelColumns {
    let level = b.key.level;
    let v = &b.voxels;
    let has_color = v.iter().any(|v| v.voxel.color_weight > 0.0);
    let edge = (1u32 << level) as f32;
    let origin = b.key.coord().map(|c| (c * BLOCK_SIZE) as f32 * edge);
    VoxelColumns {
        depth: BLOCK_DEPTH,
        morton: v.iter().map(|v| v.voxel.morton).collect(),
        faces: v.iter().map(|v| v.voxel.faces).collect(),
        normal: {
            let mut normal = Vec::new();
            oct_encode_many(v.iter().map(|v| v.voxel.normal_sum), &mut normal);
            normal
        },
        coverage: if level == 0 {
            Vec::new()
        } else {
            v.iter().map(|v| coverage_from_count(v.solid as u64, level)).collect()
        },
        color: if has_color { v.iter().map(|v| srgb8_average(&v.voxel)).collect() } else { Vec::new() },
        // The AO field's byte for each voxel, read at its centre with its normal.
        field: match field {
            Some(f) => v
                .iter()
                .map(|v| {
                    let local = local_position(&v.voxel);
                    let centre: [f32; 3] =
                        std::array::from_fn(|a| origin[a] + (local[a] as f32 + 0.5) * edge);
                    f.voxel_byte(centre, v.voxel.normal_sum)
                })
                .collect(),
            None => Vec::new(),
        },
    }
}

/// A voxel's stored colour in a block that has colour: the area-weighted
/// average as sRGB8, or the neutral grey without weight (as [`average_color`]).
fn srgb8_average(v: &crate::pipeline::voxelize::BuildVoxel) -> [u8; 3] {
    if v.color_weight > 0.0 && v.color_weight.is_finite() {
        v.color_sum.map(|c| linear_to_srgb8(c / v.color_weight))
    } else {
        NEUTRAL_SRGB8
    }
}

/// The block's tight bounds in grid units. Per axis, a coordinate's bits
/// masked out of the Morton code order the same way as the coordinate, so
/// the extremes are taken in Morton space and decoded once.
fn tight_bounds(b: &LodBlock) -> VoxelBounds {
    let base = b.key.coord().map(|c| c * BLOCK_SIZE);
    let axis: [u32; 3] = std::array::from_fn(|a| morton3(BLOCK_SIZE - 1, 0, 0) << a);
    let mut lo = axis;
    let mut hi = [0u32; 3];
    for v in &b.voxels {
        for a in 0..3 {
            let m = v.voxel.morton & axis[a];
            lo[a] = lo[a].min(m);
            hi[a] = hi[a].max(m);
        }
    }
    if b.voxels.is_empty() {
        return VoxelBounds { min: [u32::MAX; 3], max: [0; 3] };
    }
    let (lo, hi) = (lo.map(demorton3), hi.map(demorton3));
    VoxelBounds {
        min: std::array::from_fn(|a| base[a] + lo[a][a]),
        max: std::array::from_fn(|a| base[a] + hi[a][a] + 1),
    }
}

/// What a scene is made of before it is written (the in-memory reference path).
pub struct SceneContent<'a> {
    pub name: String,
    pub source: SourceInfo,
    pub grid: GridFrame,
    pub resolution_choice: ResolutionChoice,
    /// Blocks per level, finest first, each level sorted by key.
    pub levels: &'a [Vec<LodBlock>],
}

/// Writes the temporary scene's manifest and makes the scene durable. Every
/// pack was synced when it closed ([`OpenPack::close`]), so what is left is
/// the manifest and the directories' entries. Not `syncfs`: that would also
/// wait for every other writer's dirty pages on the same filesystem (on a
/// shared machine, seconds for a scene of a few files).
fn write_manifest_durably(dir: &Path, packs_dir: &Path, manifest_json: &[u8]) -> Result<(), StoreError> {
    let path = dir.join("manifest.json");
    let mut f = fs::File::create(&path).map_err(io("create", &path))?;
    f.write_all(manifest_json).map_err(io("write", &path))?;
    f.sync_all().map_err(io("sync", &path))?;
    for d in [packs_dir, dir] {
        fs::File::open(d).and_then(|f| f.sync_all()).map_err(io("sync", d))?;
    }
    Ok(())
}

/// Encodes and writes a scene held in memory (level by level, finest first),
/// then publishes it as `<store>/<id>`, replacing any previous scene of that
/// id. The build streams blocks into a [`BlockWriter`] instead; both give the
/// same files. Returns the manifest written.
pub fn write_scene(store: &Path, id: &str, content: &SceneContent) -> Result<Manifest, StoreError> {
    write_scene_reporting(store, id, content, &ProgressSink::new(&|_| {}))
}

/// [`write_scene`], reporting each block written to `progress`.
pub fn write_scene_reporting(
    store: &Path,
    id: &str,
    content: &SceneContent,
    progress: &ProgressSink,
) -> Result<Manifest, StoreError> {
    let counter = StageCounter::new(progress, Stage::Write, content.levels.iter().map(Vec::len).sum());
    let mut writer = BlockWriter::create(store, id, content.grid.resolution, REFERENCE_PENDING_BYTES)?;
    // The streaming build's order (packs hold blocks in the order they come).
    let mut blocks: Vec<&LodBlock> = content.levels.iter().flatten().collect();
    blocks.sort_by_key(|b| post_order_key(&b.key));
    for block in blocks {
        writer.add(block.clone())?;
        counter.tick();
    }
    writer.finish(
        content.name.clone(),
        content.source.clone(),
        content.grid.clone(),
        content.resolution_choice.clone(),
    )
}

/// Sorts blocks in the order the streaming pyramid finishes them: a block
/// after every block of its subtree and before the next subtree (post order
/// over the Morton order of level-0 blocks).
pub fn post_order_key(key: &BlockKey) -> (u64, u8) {
    let edge = 1u32 << key.level;
    let last = key.coord().map(|c| c * edge + edge - 1);
    (block_morton(last), key.level)
}

/// Buffer of each open pack file.
pub const PACK_BUFFER_BYTES: usize = 64 << 10;

/// A pack closes once it holds this many items (blocks and the pages sealed while it is open).
/// The goal is at most one object per 256 blocks in a bucket, where every object costs a request
/// and a listing entry; a scene's last page layers each close one small pack (a parent page names
/// its children's pack, known only once that pack is closed), so the cap is twice the goal.
pub const PACK_MAX_ITEMS: usize = 512;

/// ... or once it reaches this many bytes, whichever comes first. Past a few MB a request's
/// fixed cost (≈ one round trip) is small next to its transfer, so bigger objects save little,
/// while a bucket build holds whole packs in its upload queue ([`crate::bucket_build`]) and a
/// static host's 200-instead-of-206 answer sends a whole pack: 8 MiB bounds both. Cedar Creek's
/// blocks average about 20 KB, so its packs close on bytes at about 400 blocks.
pub const PACK_MAX_BYTES: u64 = 8 << 20;

/// Memory a held page entry takes at most (the entry with its hash string, in a `Vec`).
const HELD_ENTRY_BYTES: usize = 192;

/// Memory the writer's one open pack (its buffer) and its held pages take at most. Pages wait
/// for the open pack to close; every held page is rooted in it, so they hold at most its
/// [`PACK_MAX_ITEMS`] entries plus, for each page layer, the entries of one page filled
/// before it ([`PageBuilder`]'s notes).
pub fn pack_writer_bytes(levels: u8) -> usize {
    let layers = (levels as usize).div_ceil(PAGE_LEVELS as usize);
    let held = PACK_MAX_ITEMS + layers * voxstream_format::hierarchy::MAX_PAGE_ENTRIES as usize;
    PACK_BUFFER_BYTES + held * HELD_ENTRY_BYTES
}

/// The pack being appended to: a temporary file in `packs/`, hashed as it grows.
struct OpenPack {
    serial: u32,
    path: PathBuf,
    file: BufWriter<fs::File>,
    hasher: blake3::Hasher,
    len: u64,
    /// Blocks and pages appended.
    items: usize,
}

impl OpenPack {
    fn create(packs_dir: &Path, serial: u32) -> Result<Self, StoreError> {
        let path = packs_dir.join(format!("{serial}.open"));
        let file = fs::File::create(&path).map_err(io("create", &path))?;
        Ok(Self {
            serial,
            path,
            file: BufWriter::with_capacity(PACK_BUFFER_BYTES, file),
            hasher: blake3::Hasher::new(),
            len: 0,
            items: 0,
        })
    }

    /// Appends one block's bytes; returns their offset.
    fn append(&mut self, bytes: &[u8]) -> Result<u64, StoreError> {
        self.file.write_all(bytes).map_err(io("write", &self.path))?;
        self.hasher.update(bytes);
        let at = self.len;
        self.len += bytes.len() as u64;
        self.items += 1;
        Ok(at)
    }

    fn is_full(&self, max_bytes: u64) -> bool {
        self.items >= PACK_MAX_ITEMS || self.len >= max_bytes
    }

    /// Syncs the pack once and renames it to its content address in `scene_dir`.
    fn close(self, scene_dir: &Path) -> Result<(PackRef, PathBuf), StoreError> {
        let file = self.file.into_inner().map_err(|e| io("write", &self.path)(e.into_error()))?;
        file.sync_all().map_err(io("sync", &self.path))?;
        drop(file);
        let pack = PackRef { hash: self.hasher.finalize().to_hex().to_string(), bytes: self.len };
        let dest = scene_dir.join(pack_path(&pack.hash));
        fs::rename(&self.path, &dest).map_err(io("rename", &self.path))?;
        Ok((pack, dest))
    }
}

/// Blocks the in-memory path encodes at once.
const REFERENCE_PENDING_BYTES: usize = 256 << 20;

/// Heap bytes of a block while it waits in a [`BlockWriter`].
pub fn block_bytes(b: &LodBlock) -> usize {
    b.voxels.capacity() * std::mem::size_of::<crate::pipeline::pyramid::LodVoxel>()
}

/// Packing and encoding need at most this many bytes per voxel of the
/// blocks being encoded (packed voxel, columns, payload, lz4 output).
pub const ENCODE_BYTES_PER_VOXEL: usize = 48;

/// Takes finished blocks one at a time, in any order with children before
/// parents, packs and encodes them on all cores in batches of at most
/// `pending_limit` bytes, appends each, in the order it came, to the one open
/// pack in a temporary scene directory (closed at [`PACK_MAX_ITEMS`] items
/// or [`PACK_MAX_BYTES`], and at the end), feeds its entry to the
/// [`PageBuilder`] (which seals a page once its root came and its packs are
/// closed; the writer then writes it) and drops it. The packs' bytes depend on
/// the order blocks come in: the build gives post order ([`post_order_key`]),
/// which also keeps the held pages few. [`BlockWriter::finish`] writes the
/// manifest last and publishes the scene atomically; dropped before that, the
/// writer removes what it wrote.
pub struct BlockWriter {
    store: PathBuf,
    id: String,
    tmp: PathBuf,
    packs_dir: PathBuf,
    /// The pack being filled, if any.
    pack: Option<OpenPack>,
    /// Serial of the next pack to open.
    next_pack: u32,
    /// [`PACK_MAX_BYTES`] (tests lower it).
    pack_max_bytes: u64,
    packs_closed: usize,
    pending: Vec<LodBlock>,
    pending_bytes: usize,
    pending_limit: usize,
    pages: PageBuilder,
    written: usize,
    levels: Vec<LevelInfo>,
    /// Union of the level-0 blocks' tight bounds (the manifest's `bounds`).
    bounds: Option<VoxelBounds>,
    /// Bytes of the pages placed so far (the manifest's `page_bytes`).
    page_bytes: u64,
    published: bool,
    /// Told of each pack and page as it is finished.
    pub finished_files: Option<crate::pipeline::FinishedFiles>,
    /// Told of the publish before the replaced scene is removed.
    pub on_published: Option<crate::pipeline::OnPublished>,
    /// The AO field the blocks were encoded with, recorded in the manifest.
    pub ao_field: Option<voxstream_format::AoFieldInfo>,
}

impl BlockWriter {
    pub fn create(store: &Path, id: &str, resolution: u32, pending_limit: usize) -> Result<Self, StoreError> {
        validate_id(id)?;
        fs::create_dir_all(store).map_err(io("create directory", store))?;
        let tmp = store.join(format!(
            ".tmp-{id}-{}-{}",
            std::process::id(),
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos())
        ));
        let packs_dir = tmp.join("packs");
        let levels = level_count(resolution);
        let writer = Self {
            store: store.to_path_buf(),
            id: id.to_string(),
            tmp,
            packs_dir,
            pack: None,
            next_pack: 0,
            pack_max_bytes: PACK_MAX_BYTES,
            packs_closed: 0,
            pending: Vec::new(),
            pending_bytes: 0,
            pending_limit,
            pages: PageBuilder::new(levels - 1, PAGE_LEVELS).with_pages_in_packs(),
            written: 0,
            levels: (0..levels)
                .map(|l| LevelInfo { level: l, resolution: resolution >> l, blocks: 0, voxels: 0, bytes: 0 })
                .collect(),
            bounds: None,
            page_bytes: 0,
            published: false,
            finished_files: None,
            on_published: None,
            ao_field: None,
        };
        fs::create_dir_all(&writer.packs_dir).map_err(io("create directory", &writer.packs_dir))?;
        Ok(writer)
    }

    /// Queues a finished block (buried voxels already dropped, not empty).
    pub fn add(&mut self, block: LodBlock) -> Result<(), StoreError> {
        debug_assert!(!block.voxels.is_empty() && block.voxels.iter().all(|v| v.voxel.faces != 0));
        let bytes = block_bytes(&block);
        if self.pending_bytes + bytes > self.pending_limit {
            self.flush()?;
        }
        self.pending_bytes += bytes;
        self.pending.push(block);
        Ok(())
    }

    /// Bytes of the blocks waiting to be encoded.
    pub fn pending_bytes(&self) -> usize {
        self.pending_bytes
    }

    /// Encodes every queued block, on all cores, then appends them to their
    /// packs and records their entries in queue order (children before parents).
    pub fn flush(&mut self) -> Result<(), StoreError> {
        let encoded: Vec<(BlockEntry, Vec<u8>)> =
            std::mem::take(&mut self.pending).into_par_iter().map(|b| encode_entry(&b)).collect();
        self.pending_bytes = 0;
        for (e, bytes) in encoded {
            self.place(e, &bytes)?;
        }
        Ok(())
    }

    /// Writes a block already encoded by [`encode_entry`] (e.g. on the worker
    /// that made it), after every block queued before it.
    pub fn add_encoded(&mut self, entry: BlockEntry, bytes: &[u8]) -> Result<(), StoreError> {
        if !self.pending.is_empty() {
            self.flush()?;
        }
        self.place(entry, bytes)
    }

    /// Appends one encoded block to the open pack (opening one if needed),
    /// records its entry, and closes the pack once it is full.
    fn place(&mut self, mut e: BlockEntry, bytes: &[u8]) -> Result<(), StoreError> {
        let level = self.levels.get_mut(e.key.level as usize).ok_or_else(|| StoreError::Damaged {
            id: self.id.clone(),
            message: format!("block {} lies beyond the grid's levels", e.key),
        })?;
        level.blocks += 1;
        level.voxels += e.voxels as u64;
        level.bytes += e.bytes as u64;
        self.written += 1;
        if e.key.level == 0 {
            let b = self.bounds.get_or_insert(e.bounds);
            for a in 0..3 {
                b.min[a] = b.min[a].min(e.bounds.min[a]);
                b.max[a] = b.max[a].max(e.bounds.max[a]);
            }
        }
        let pack = self.open_pack()?;
        e.location = BlockLocation { pack: pack.serial, offset: pack.append(bytes)? };
        let pages = self.pages.add(e).map_err(page_err)?;
        self.place_pages(pages)?;
        if self.pack.as_ref().is_some_and(|p| p.is_full(self.pack_max_bytes)) {
            self.close_pack()?;
        }
        Ok(())
    }

    /// The pack being filled, opened if there is none.
    fn open_pack(&mut self) -> Result<&mut OpenPack, StoreError> {
        match self.pack.take() {
            Some(p) => Ok(self.pack.insert(p)),
            None => {
                let serial = self.next_pack;
                self.next_pack += 1;
                Ok(self.pack.insert(OpenPack::create(&self.packs_dir, serial)?))
            }
        }
    }

    /// Closes the open pack (synced, renamed to its content address, handed to
    /// `finished_files`) and appends the pages that were waiting for it to the next pack.
    fn close_pack(&mut self) -> Result<(), StoreError> {
        let Some(open) = self.pack.take() else { return Ok(()) };
        let serial = open.serial;
        let (pack, path) = open.close(&self.tmp)?;
        if let Some(sink) = &self.finished_files {
            // Read back from the page cache: the writer holds no pack in memory.
            let bytes = fs::read(&path).map_err(io("read", &path))?;
            (sink.0)(&pack_path(&pack.hash), bytes).map_err(|e| self.sink_failed(e))?;
        }
        self.packs_closed += 1;
        let pages = self.pages.pack_closed(serial, pack).map_err(page_err)?;
        self.place_pages(pages)
    }

    /// Appends sealed pages to the open pack (opened if needed) and tells the page builder where
    /// they are: pages are items of packs like blocks, so a scene is one object per pack.
    fn place_pages(
        &mut self,
        pages: Vec<voxstream_format::hierarchy::FinishedPage>,
    ) -> Result<(), StoreError> {
        for (page_ref, bytes) in pages {
            self.page_bytes += bytes.len() as u64;
            let pack = self.open_pack()?;
            let (serial, offset) = (pack.serial, pack.append(&bytes)?);
            self.pages.page_placed(page_ref.root, serial, offset).map_err(page_err)?;
        }
        Ok(())
    }

    fn sink_failed(&self, message: String) -> StoreError {
        StoreError::Damaged { id: self.id.clone(), message }
    }

    /// Packs closed so far.
    pub fn packs_closed(&self) -> usize {
        self.packs_closed
    }

    /// Entries of pages held until the open pack closes.
    pub fn held_page_entries(&self) -> usize {
        self.pages.held_entries()
    }

    /// Blocks written so far.
    pub fn blocks_written(&self) -> usize {
        self.written
    }

    /// Writes the last blocks and pages and the manifest, then publishes the
    /// scene as `<store>/<id>`, replacing any previous scene of that id.
    pub fn finish(
        mut self,
        name: String,
        source: SourceInfo,
        grid: GridFrame,
        resolution_choice: ResolutionChoice,
    ) -> Result<Manifest, StoreError> {
        self.flush()?;
        // Each close can seal the next page layer into a new pack; the root page's pack ends it.
        while self.pack.is_some() {
            self.close_pack()?;
        }
        let pages = std::mem::replace(&mut self.pages, PageBuilder::new(0, PAGE_LEVELS));
        let top = pages.finish().map_err(page_err)?;
        let manifest = Manifest {
            format_version: FORMAT_VERSION,
            name,
            source,
            grid,
            block_size: BLOCK_SIZE,
            levels: std::mem::take(&mut self.levels),
            resolution_choice,
            page_levels: PAGE_LEVELS,
            root: top.root,
            root_page: top.root_page,
            root_pack: top.root_pack,
            root_page_pack: top.root_page_pack,
            ao_field: self.ao_field.clone(),
            bounds: self.bounds,
            page_bytes: Some(self.page_bytes),
        };
        write_manifest_durably(&self.tmp, &self.packs_dir, &manifest.to_json())?;
        let on_published = |id: &str| {
            if let Some(hook) = &self.on_published {
                (hook.0)(id)
            }
        };
        publish(&self.store, &self.id, &self.tmp, on_published)?;
        self.published = true;
        Ok(manifest)
    }
}

fn page_err(e: PageError) -> StoreError {
    StoreError::Damaged { id: "(being written)".into(), message: format!("hierarchy: {e}") }
}

/// Packs and encodes one block; returns its entry (child mask still 0: the
/// page builder fills it in; location still a file: the writer places it)
/// and its bytes.
pub fn encode_entry(b: &LodBlock) -> (BlockEntry, Vec<u8>) {
    encode_entry_with(b, None, None)
}

/// [`encode_entry`] for a block the pyramid drew ([`DrawnBlock`]), with the
/// AO field's column when there is a field: the pyramid's face prediction
/// spares the codec its own neighbour lookups.
pub fn encode_drawn_entry(d: &DrawnBlock, field: Option<&AoField>) -> (BlockEntry, Vec<u8>) {
    encode_entry_with(&d.block, Some(&d.prediction), field)
}

fn encode_entry_with(
    b: &LodBlock,
    prediction: Option<&[u8]>,
    field: Option<&AoField>,
) -> (BlockEntry, Vec<u8>) {
    let columns = block_columns(b, field);
    let bytes = encode_columns(b.key, &columns, prediction);
    let entry = BlockEntry {
        key: b.key,
        bounds: tight_bounds(b),
        voxels: columns.len() as u32,
        faces: columns.faces.iter().map(|f| f.count_ones()).sum(),
        bytes: bytes.len() as u32,
        hash: blake3::hash(&bytes).to_hex().to_string(),
        geometric_error: b.geometric_error(),
        child_mask: 0,
        location: BlockLocation::FILE,
    };
    (entry, bytes)
}

impl Drop for BlockWriter {
    fn drop(&mut self) {
        if !self.published {
            // A failed or cancelled build leaves nothing behind.
            let _ = fs::remove_dir_all(&self.tmp);
        }
    }
}

/// Renames `tmp` to `<store>/<id>`, then calls `on_published`, then removes the scene it
/// replaced: a server that re-reads the manifest in `on_published` never serves an old manifest
/// whose blocks are already gone.
fn publish(store: &Path, id: &str, tmp: &Path, on_published: impl FnOnce(&str)) -> Result<(), StoreError> {
    let dest = store.join(id);
    let replaced = if dest.exists() {
        // One atomic swap where the kernel offers it, so a reader never finds the
        // scene missing; the old scene then sits at `tmp` until removed (a crash
        // leaves it as a `.tmp-*` dir, which start-up cleanup removes).
        if exchange_dirs(tmp, &dest).is_ok() {
            Some(tmp.to_path_buf())
        } else {
            // Move the old scene aside first: rename cannot replace a non-empty directory.
            let old = store.join(format!(".old-{id}-{}", std::process::id()));
            fs::rename(&dest, &old).map_err(io("move aside", &dest))?;
            fs::rename(tmp, &dest).map_err(io("publish", &dest))?;
            Some(old)
        }
    } else {
        fs::rename(tmp, &dest).map_err(io("publish", &dest))?;
        None
    };
    let synced = fs::File::open(store).and_then(|d| d.sync_all()).map_err(io("sync", store));
    on_published(id);
    if let Some(old) = replaced {
        let _ = fs::remove_dir_all(old);
    }
    synced
}

/// Atomically swaps two directories (Linux `renameat2(RENAME_EXCHANGE)`).
#[cfg(target_os = "linux")]
fn exchange_dirs(a: &Path, b: &Path) -> std::io::Result<()> {
    use std::ffi::CString;
    use std::os::unix::ffi::OsStrExt;
    let a = CString::new(a.as_os_str().as_bytes())?;
    let b = CString::new(b.as_os_str().as_bytes())?;
    // SAFETY: both are valid NUL-terminated paths that outlive the call.
    let r = unsafe {
        libc::renameat2(libc::AT_FDCWD, a.as_ptr(), libc::AT_FDCWD, b.as_ptr(), libc::RENAME_EXCHANGE)
    };
    if r == 0 { Ok(()) } else { Err(std::io::Error::last_os_error()) }
}

#[cfg(not(target_os = "linux"))]
fn exchange_dirs(_a: &Path, _b: &Path) -> std::io::Result<()> {
    Err(std::io::Error::from(std::io::ErrorKind::Unsupported))
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use voxstream_format::BlockKey;

    use super::*;

    /// One voxel a block, for every block of a tree over a diagonal of
    /// level-0 blocks (`n` of them) up to the single root on `coarsest`.
    fn diagonal_tree(n: u32, coarsest: u8) -> Vec<LodBlock> {
        use crate::pipeline::pyramid::LodVoxel;
        use crate::pipeline::voxelize::BuildVoxel;
        let voxel = LodVoxel {
            voxel: BuildVoxel {
                morton: 0,
                normal_sum: [0.0, 0.0, 1.0],
                color_sum: [0.0; 3],
                color_weight: 0.0,
                faces: 1,
            },
            solid: 1,
            error: 0.0,
        };
        let mut keys = std::collections::BTreeSet::new();
        for i in 0..n {
            let mut k = BlockKey::new(0, i, i, i);
            keys.insert(k);
            while k.level < coarsest {
                k = k.parent();
                keys.insert(k);
            }
        }
        keys.into_iter().map(|key| LodBlock { key, voxels: vec![voxel] }).collect()
    }

    /// Writes `blocks` in the order given; returns the manifest, the packs' block counts in
    /// the order they closed, and the most page entries held at once.
    fn write_packed(
        blocks: &[LodBlock],
        store: &Path,
        resolution: u32,
        pack_max_bytes: u64,
    ) -> (Manifest, Vec<usize>, usize) {
        let mut w = BlockWriter::create(store, "t", resolution, 1).unwrap();
        w.pack_max_bytes = pack_max_bytes;
        let (mut per_pack, mut in_pack, mut most_held) = (Vec::new(), 0, 0);
        for b in blocks {
            w.add(b.clone()).unwrap();
            w.flush().unwrap();
            in_pack += 1;
            if w.packs_closed() > per_pack.len() {
                per_pack.push(in_pack);
                in_pack = 0;
            }
            most_held = most_held.max(w.held_page_entries());
        }
        let m = w
            .finish(
                "t".into(),
                SourceInfo { file: "t".into(), format: "obj".into(), triangles: 1, skipped_triangles: 0 },
                GridFrame { origin: [0.0; 3], voxel_size: 1.0, resolution, units: None },
                ResolutionChoice {
                    mode: "explicit".into(),
                    resolution,
                    voxel_size: 1.0,
                    median_edge: None,
                    reason: "test".into(),
                },
            )
            .unwrap();
        if in_pack > 0 {
            per_pack.push(in_pack);
        }
        (m, per_pack, most_held)
    }

    /// Packs hold [`PACK_MAX_ITEMS`] items each (blocks and the pages sealed while they were
    /// open), span pages, and the scene has no page files: every page and block reads back from a
    /// pack range. The pages held for the open pack stay within the bound
    /// [`MemoryPlan`](crate::pipeline::MemoryPlan) counts. Control: with a tiny byte cap the packs
    /// close on bytes instead, one item each.
    #[test]
    fn packs_span_pages_and_close_at_the_item_cap() {
        let (resolution, coarsest) = (65536, 10);
        let mut blocks = diagonal_tree(1024, coarsest);
        blocks.sort_by_key(|b| post_order_key(&b.key));
        let dir = tempfile::tempdir().unwrap();
        let (manifest, per_pack, most_held) = write_packed(&blocks, dir.path(), resolution, PACK_MAX_BYTES);
        let layers = (level_count(resolution) as usize).div_ceil(PAGE_LEVELS as usize);
        let bound = PACK_MAX_ITEMS + layers * voxstream_format::hierarchy::MAX_PAGE_ENTRIES as usize;
        assert!(most_held > 0 && most_held <= bound, "{most_held} entries held, bound {bound}");
        assert!(pack_writer_bytes(level_count(resolution)) >= bound * HELD_ENTRY_BYTES);
        let scene = crate::store::open_scene(dir.path(), "t").unwrap();
        assert_eq!(scene.manifest, manifest);
        assert_eq!(scene.blocks().len(), blocks.len());
        assert!(!dir.path().join("t/pages").exists(), "pages live in packs");
        let pages = scene.index.read().pages_loaded();
        let packs = std::fs::read_dir(dir.path().join("t/packs")).unwrap().count();
        let items = blocks.len() + pages;
        // Full packs but for the last few: each page layer's last pages close one more pack.
        assert!(
            (items.div_ceil(PACK_MAX_ITEMS)..=items.div_ceil(PACK_MAX_ITEMS) + layers).contains(&packs),
            "{packs} packs for {items} items"
        );
        assert!(pages > 2 * packs, "{pages} pages, {packs} packs: packs span pages");
        assert!(per_pack.iter().all(|&n| n <= PACK_MAX_ITEMS), "{per_pack:?}");
        assert_eq!(scene.index.read().packs().count(), packs);
        for e in scene.blocks() {
            let bytes = scene.read_block(&e).unwrap();
            assert_eq!(voxstream_format::decode_block(&bytes).unwrap().key, e.key);
        }
        // Control: a byte cap below one block's size closes a pack after every block (with the
        // pages sealed by it), where the default cap needs one pack.
        let mut small = diagonal_tree(64, 6);
        small.sort_by_key(|b| post_order_key(&b.key));
        let dir = tempfile::tempdir().unwrap();
        write_packed(&small, dir.path(), 4096, 1);
        crate::store::open_scene(dir.path(), "t").unwrap();
        let packs = std::fs::read_dir(dir.path().join("t/packs")).unwrap().count();
        assert!(packs >= small.len(), "{packs} packs for {} blocks", small.len());
    }

    /// A page's blocks and child pages may lie in more packs than it has entries: a child page
    /// waits for the pack holding its last entries to close, so it lands in the pack after its
    /// root block's. Scenes of many packs do this (the conference room at 32768: a page of 104
    /// entries naming 172 packs), and readers once refused such pages, so nothing below the top
    /// page could be drawn or served. Here packs of a few blocks force it; every page must read
    /// back and every block with it. Control: the surplus of packs over entries is positive.
    #[test]
    fn pages_naming_more_packs_than_entries_read_back() {
        let mut blocks = diagonal_tree(48, 8);
        blocks.sort_by_key(|b| post_order_key(&b.key));
        let mut most_surplus = i64::MIN;
        let one_block = {
            let dir = tempfile::tempdir().unwrap();
            let (m, _, _) = write_packed(&blocks, dir.path(), 16384, PACK_MAX_BYTES);
            m.root.bytes as u64
        };
        for blocks_a_pack in [2, 3] {
            let dir = tempfile::tempdir().unwrap();
            write_packed(&blocks, dir.path(), 16384, blocks_a_pack * one_block);
            let scene = crate::store::open_scene(dir.path(), "t").unwrap();
            assert_eq!(scene.blocks().len(), blocks.len());
            for e in scene.blocks() {
                assert_eq!(
                    voxstream_format::decode_block(&scene.read_block(&e).unwrap()).unwrap().key,
                    e.key
                );
            }
            let scene_dir = dir.path().join("t");
            voxstream_format::load_scene_index(&scene.manifest, |r, range| {
                let bytes = crate::store::read_pack_range(&scene_dir, &range.expect("pages live in packs"))?;
                let page =
                    voxstream_format::HierarchyPage::decode(&bytes, r).map_err(std::io::Error::other)?;
                most_surplus = most_surplus.max(page.packs.len() as i64 - page.entries.len() as i64);
                Ok::<_, std::io::Error>(bytes)
            })
            .unwrap();
        }
        assert!(most_surplus > 0, "no page names more packs than entries: {most_surplus}");
    }

    /// Every directory of a store by the manifest text it holds.
    fn manifests_in(store: &Path) -> BTreeMap<String, String> {
        fs::read_dir(store)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter_map(|d| {
                let text = fs::read_to_string(d.join("manifest.json")).ok()?;
                Some((d.file_name()?.to_str()?.to_string(), text))
            })
            .collect()
    }

    /// Fails if the replaced scene is removed before the hook runs (a server re-reading the
    /// manifest there would have served blocks that were already gone) or is never removed.
    #[test]
    fn publish_calls_back_before_removing_the_replaced_scene() {
        let store = tempfile::tempdir().unwrap();
        let staged = |name: &str, text: &str| {
            let d = store.path().join(name);
            fs::create_dir_all(&d).unwrap();
            fs::write(d.join("manifest.json"), text).unwrap();
            d
        };
        let mut seen = Vec::new();
        publish(store.path(), "s", &staged(".tmp-1", "old"), |id| {
            seen.push((id.to_string(), manifests_in(store.path())))
        })
        .unwrap();
        publish(store.path(), "s", &staged(".tmp-2", "new"), |id| {
            seen.push((id.to_string(), manifests_in(store.path())))
        })
        .unwrap();
        // Control: the first publish replaced nothing, so only the new scene was there.
        assert_eq!(seen[0], ("s".to_string(), BTreeMap::from([("s".to_string(), "old".to_string())])));
        let (id, during) = &seen[1];
        assert_eq!(id, "s");
        assert_eq!(during.get("s").map(String::as_str), Some("new"));
        assert!(
            during.values().any(|m| m == "old"),
            "the replaced scene was gone during the hook: {during:?}"
        );
        assert_eq!(manifests_in(store.path()), BTreeMap::from([("s".to_string(), "new".to_string())]));
    }

    /// Fails if the columns taken straight from the voxels differ from those
    /// of the packed block (the definition), or the entry's bounds and face
    /// count from those of the packed voxels: random blocks on levels 0–3,
    /// with and without colour (weights zero, positive, infinite, NaN), with
    /// buried and zero-sum voxels.
    #[test]
    fn entries_match_the_packed_block() {
        use crate::pipeline::pyramid::LodVoxel;
        use crate::pipeline::voxelize::BuildVoxel;
        use rand::{Rng, SeedableRng, rngs::StdRng};
        let mut rng = StdRng::seed_from_u64(8);
        for round in 0..300 {
            let level = (round % 4) as u8;
            let colored = round % 3 != 0;
            let n = [1, 2, 50, 3000][round % 4];
            let mut morton: Vec<u32> = (0..n).map(|_| rng.random_range(0..1u32 << 18)).collect();
            morton.sort_unstable();
            morton.dedup();
            let voxels: Vec<LodVoxel> = morton
                .iter()
                .map(|&m| {
                    let w = match rng.random_range(0..8) {
                        0 => 0.0,
                        1 => f32::INFINITY,
                        2 => f32::NAN,
                        _ => rng.random_range(0.0..5.0),
                    };
                    let normal_sum = if rng.random_range(0..20) == 0 {
                        [0.0; 3]
                    } else {
                        std::array::from_fn(|_| rng.random_range(-100.0..100.0))
                    };
                    LodVoxel {
                        voxel: BuildVoxel {
                            morton: m,
                            normal_sum,
                            color_sum: if colored {
                                std::array::from_fn(|_| rng.random_range(0.0..5.0))
                            } else {
                                [0.0; 3]
                            },
                            color_weight: if colored { w } else { 0.0 },
                            faces: rng.random_range(1..64),
                        },
                        solid: if level == 0 { 1 } else { rng.random_range(1..=1u32 << (3 * level)) },
                        error: 0.0,
                    }
                })
                .collect();
            let b = LodBlock { key: BlockKey::new(level, 3, 1, 2), voxels };
            let packed = packed_block(&b);
            assert_eq!(block_columns(&b, None), VoxelColumns::from_block(&packed), "round {round}");
            let (entry, bytes) = encode_entry(&b);
            assert_eq!(bytes, voxstream_format::encode_block(&packed), "round {round}");
            let base = b.key.coord().map(|c| c * BLOCK_SIZE);
            let mut min = [u32::MAX; 3];
            let mut max = [0u32; 3];
            for v in &packed.voxels {
                let p = v.local();
                for a in 0..3 {
                    min[a] = min[a].min(base[a] + p[a]);
                    max[a] = max[a].max(base[a] + p[a] + 1);
                }
            }
            assert_eq!(entry.bounds, VoxelBounds { min, max }, "round {round}");
            assert_eq!((entry.voxels, entry.faces), (packed.voxels.len() as u32, packed.face_count()));
        }
    }

    #[test]
    fn srgb_conversion() {
        assert_eq!(linear_to_srgb8(0.0), 0);
        assert_eq!(linear_to_srgb8(1.0), 255);
        assert_eq!(linear_to_srgb8(0.22), 129);
        assert_eq!(linear_to_srgb8(f32::NAN), 0);
        assert_eq!(linear_to_srgb8(7.0), 255);
    }

    #[test]
    fn packing_averages_normals_and_colours() {
        use crate::pipeline::pyramid::LodVoxel;
        use crate::pipeline::voxelize::BuildVoxel;
        let voxel = |m, w: f32| LodVoxel {
            voxel: BuildVoxel {
                morton: m,
                normal_sum: [0.0, 0.0, -40.0],
                color_sum: [0.5 * w, 0.0, w],
                color_weight: w,
                faces: 1,
            },
            solid: 3,
            error: 2.0,
        };
        let b = LodBlock { key: BlockKey::new(1, 0, 0, 0), voxels: vec![voxel(0, 4.0), voxel(9, 0.0)] };
        let p = packed_block(&b);
        assert_eq!(voxstream_format::oct_decode(p.voxels[0].normal), [0.0, 0.0, -1.0]);
        assert_eq!(p.voxels[0].color(), Some([188, 0, 255]));
        assert_eq!(p.voxels[1].color(), Some(NEUTRAL_SRGB8), "uncoloured voxel in a coloured block");
        assert_eq!(p.voxels[0].coverage(), 96, "3 of 8");
        assert_eq!(b.geometric_error(), 2.0);
        let grey = LodBlock { key: BlockKey::new(0, 0, 0, 0), voxels: vec![voxel(0, 0.0)] };
        assert_eq!(packed_block(&grey).voxels[0].color(), None);
    }
}
