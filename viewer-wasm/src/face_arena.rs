//! The face arena: where every resident block's face records live on the GPU.
//! A few large chunks, each one face buffer, one page table and one buffer of
//! indirect draw args, carved into pages of [`PAGE_FACES`] faces. A block takes
//! a run of pages in one chunk. Why: a buffer and two bind groups a block cost
//! the browser's main thread tens of microseconds each (every WebGPU call
//! crosses from wasm into JavaScript and on to the GPU process), so at a
//! thousand blocks a view the upload was the longest thing a streaming frame
//! did. Here a new block creates no WebGPU object: the chunk's bind groups are
//! made once, the block's draw is one `draw_indirect` at its first page's args,
//! and the vertex shader finds the block's origin in the page table by the face
//! it draws (Bevy's meshlet renderer keeps its meshlets in one persistent buffer
//! the same way).
//!
//! Invariants:
//! - a chunk's free runs are sorted by start, disjoint and coalesced (no two touch);
//! - a page belongs to at most one block, and its table entry names that block
//!   (written by the expansion, shaders/expand.wgsl);
//! - the args of a block's first page are `(6 × faces, 1, 6 × first face, 0)`
//!   once its expansion has run.

use crate::expand::FACE_RECORD_BYTES;

/// Faces a page holds.
pub const PAGE_FACES: u32 = 256;
/// Bytes of a page's entry in its chunk's page table (shaders: `PageInfo`).
pub const PAGE_INFO_BYTES: u64 = 32;
/// Bytes of a page's slot of indirect draw args (only a block's first page's is used).
pub const PAGE_ARGS_BYTES: u64 = 16;
/// GPU bytes a page takes, its faces, table entry and args together.
pub const PAGE_BYTES: u64 = PAGE_FACES as u64 * FACE_RECORD_BYTES + PAGE_INFO_BYTES + PAGE_ARGS_BYTES;

/// Pages a block of `faces` faces takes (at least one).
pub fn pages_for(faces: u32) -> u32 {
    faces.max(1).div_ceil(PAGE_FACES)
}

/// Where a resident block's faces are: a run of pages in one chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct BlockSlot {
    pub chunk: u32,
    pub first_page: u32,
    pub pages: u32,
}

impl BlockSlot {
    /// Index of the block's first face in its chunk's face buffer.
    pub fn first_face(&self) -> u32 {
        self.first_page * PAGE_FACES
    }

    /// Byte offset of the block's draw args in its chunk's args buffer.
    pub fn args_offset(&self) -> u64 {
        self.first_page as u64 * PAGE_ARGS_BYTES
    }

    pub fn bytes(&self) -> u64 {
        self.pages as u64 * PAGE_BYTES
    }
}

/// The free runs of pages of one chunk, best fit. Invariant: sorted by start,
/// disjoint, coalesced; `used` is the pages not in them.
#[derive(Debug, Clone)]
pub struct PageRuns {
    pages: u32,
    /// (first page, length)
    free: Vec<(u32, u32)>,
    used: u32,
}

impl PageRuns {
    pub fn new(pages: u32) -> Self {
        Self { pages, free: if pages > 0 { vec![(0, pages)] } else { Vec::new() }, used: 0 }
    }

    pub fn pages(&self) -> u32 {
        self.pages
    }

    pub fn used(&self) -> u32 {
        self.used
    }

    pub fn is_empty(&self) -> bool {
        self.used == 0
    }

    /// The longest free run.
    pub fn largest_free(&self) -> u32 {
        self.free.iter().map(|r| r.1).max().unwrap_or(0)
    }

    /// Takes `pages` from the smallest free run that holds them (best fit, so
    /// large runs stay whole for large blocks); returns the first page.
    pub fn take(&mut self, pages: u32) -> Option<u32> {
        let (i, &(start, len)) =
            self.free.iter().enumerate().filter(|(_, r)| r.1 >= pages).min_by_key(|(_, r)| r.1)?;
        if len == pages {
            self.free.remove(i);
        } else {
            self.free[i] = (start + pages, len - pages);
        }
        self.used += pages;
        Some(start)
    }

    /// Gives back a run [`PageRuns::take`] handed out, merging it with the free runs it touches.
    pub fn give(&mut self, start: u32, pages: u32) {
        let i = self.free.partition_point(|r| r.0 < start);
        debug_assert!(i == 0 || self.free[i - 1].0 + self.free[i - 1].1 <= start, "run given back twice");
        debug_assert!(i == self.free.len() || start + pages <= self.free[i].0, "run given back twice");
        self.used -= pages;
        let joins_before = i > 0 && self.free[i - 1].0 + self.free[i - 1].1 == start;
        let joins_after = i < self.free.len() && start + pages == self.free[i].0;
        match (joins_before, joins_after) {
            (true, true) => {
                self.free[i - 1].1 += pages + self.free[i].1;
                self.free.remove(i);
            }
            (true, false) => self.free[i - 1].1 += pages,
            (false, true) => self.free[i] = (start, pages + self.free[i].1),
            (false, false) => self.free.insert(i, (start, pages)),
        }
    }
}

/// One chunk's GPU side: faces, page table, args, and the bind groups that read them.
pub struct FaceChunk {
    pub faces: wgpu::Buffer,
    pub page_table: wgpu::Buffer,
    pub args: wgpu::Buffer,
    /// Group 1 of the draw pipelines (voxel.wgsl): page table + faces.
    pub draw_group: wgpu::BindGroup,
    /// The expansion's group (expand.wgsl), made on the chunk's first upload.
    pub expand_group: Option<wgpu::BindGroup>,
    pub runs: PageRuns,
}

impl FaceChunk {
    fn new(device: &wgpu::Device, draw_layout: &wgpu::BindGroupLayout, pages: u32) -> Self {
        let buffer = |label, size, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        // COPY_SRC lets tests read the records back.
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let faces = buffer("arena faces", pages as u64 * PAGE_FACES as u64 * FACE_RECORD_BYTES, storage);
        let page_table = buffer("arena page table", pages as u64 * PAGE_INFO_BYTES, storage);
        let args = buffer(
            "arena draw args",
            pages as u64 * PAGE_ARGS_BYTES,
            storage | wgpu::BufferUsages::INDIRECT | wgpu::BufferUsages::COPY_DST,
        );
        let draw_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("arena draw"),
            layout: draw_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: page_table.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: faces.as_entire_binding() },
            ],
        });
        Self { faces, page_table, args, draw_group, expand_group: None, runs: PageRuns::new(pages) }
    }

    pub fn bytes(&self) -> u64 {
        self.runs.pages() as u64 * PAGE_BYTES
    }

    fn destroy(&self) {
        self.faces.destroy();
        self.page_table.destroy();
        self.args.destroy();
    }
}

/// Every chunk, addressed by [`BlockSlot::chunk`]; an empty chunk stays (a
/// block that comes back creates nothing) until the budget needs its bytes.
#[derive(Default)]
pub struct FaceArena {
    chunks: Vec<Option<FaceChunk>>,
    bytes: u64,
}

impl FaceArena {
    /// Bytes of every chunk, used or not.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    pub fn chunk(&self, index: u32) -> Option<&FaceChunk> {
        self.chunks.get(index as usize)?.as_ref()
    }

    pub fn chunk_mut(&mut self, index: u32) -> Option<&mut FaceChunk> {
        self.chunks.get_mut(index as usize)?.as_mut()
    }

    pub fn chunk_count(&self) -> usize {
        self.chunks.iter().flatten().count()
    }

    /// A run of `pages` in the chunk that fits it best, if any has one.
    pub fn take(&mut self, pages: u32) -> Option<BlockSlot> {
        let (chunk, _) = self
            .chunks
            .iter()
            .enumerate()
            .filter_map(|(i, c)| Some((i, c.as_ref()?.runs.largest_free())))
            .filter(|&(_, free)| free >= pages)
            .min_by_key(|&(_, free)| free)?;
        let first_page = self.chunks[chunk].as_mut()?.runs.take(pages)?;
        Some(BlockSlot { chunk: chunk as u32, first_page, pages })
    }

    pub fn give(&mut self, slot: BlockSlot) {
        if let Some(c) = self.chunk_mut(slot.chunk) {
            c.runs.give(slot.first_page, slot.pages);
        }
    }

    /// Adds an empty chunk of `pages` pages.
    pub fn add_chunk(&mut self, device: &wgpu::Device, draw_layout: &wgpu::BindGroupLayout, pages: u32) {
        let chunk = FaceChunk::new(device, draw_layout, pages);
        self.bytes += chunk.bytes();
        match self.chunks.iter().position(Option::is_none) {
            Some(i) => self.chunks[i] = Some(chunk),
            None => self.chunks.push(Some(chunk)),
        }
    }

    /// Destroys one chunk no block uses; false when every chunk is in use.
    pub fn drop_empty_chunk(&mut self) -> bool {
        let Some(i) = self.chunks.iter().position(|c| c.as_ref().is_some_and(|c| c.runs.is_empty())) else {
            return false;
        };
        if let Some(c) = self.chunks[i].take() {
            self.bytes -= c.bytes();
            c.destroy();
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Free runs as they must be: sorted, disjoint, coalesced, and with the used pages adding up.
    fn check(runs: &PageRuns) {
        for w in runs.free.windows(2) {
            assert!(w[0].0 + w[0].1 < w[1].0, "runs {:?} overlap or touch", runs.free);
        }
        let free: u32 = runs.free.iter().map(|r| r.1).sum();
        assert_eq!(free + runs.used, runs.pages);
    }

    #[test]
    fn page_runs_fit_best_and_coalesce_on_return() {
        let mut runs = PageRuns::new(100);
        let a = runs.take(10).unwrap();
        let b = runs.take(20).unwrap();
        let c = runs.take(30).unwrap();
        assert_eq!((a, b, c), (0, 10, 30));
        check(&runs);
        // Holes of 10 (a) and 30 (c) besides the tail of 40: 25 goes in c's hole, the best fit.
        runs.give(a, 10);
        runs.give(c, 30);
        check(&runs);
        assert_eq!(runs.take(25), Some(30));
        // 10 goes in a's hole, not the tail.
        assert_eq!(runs.take(10), Some(0));
        check(&runs);
        // What is left of c's hole joined the tail: 45 pages from 55.
        assert_eq!(runs.largest_free(), 45);
        assert_eq!(runs.take(46), None, "no run holds 46 pages");
        // Everything back: one run again, whatever the order.
        runs.give(0, 10);
        runs.give(30, 25);
        runs.give(b, 20);
        check(&runs);
        assert!(runs.is_empty());
        assert_eq!(runs.free, vec![(0, 100)]);
        // Control: a fragmented chunk with enough free pages in all still refuses a long run.
        let mut frag = PageRuns::new(9);
        let starts: Vec<u32> = (0..9).map(|_| frag.take(1).unwrap()).collect();
        for s in starts.iter().step_by(2) {
            frag.give(*s, 1);
        }
        check(&frag);
        assert_eq!(frag.take(2), None);
        assert_eq!(frag.take(1), Some(0));
    }

    #[test]
    fn a_block_takes_whole_pages() {
        assert_eq!(pages_for(0), 1);
        assert_eq!(pages_for(1), 1);
        assert_eq!(pages_for(PAGE_FACES), 1);
        assert_eq!(pages_for(PAGE_FACES + 1), 2);
        // The most faces a 64³ block can have (a checkerboard of voxels, six faces each).
        assert_eq!(pages_for(64 * 64 * 64 / 2 * 6), 3072);
        let slot = BlockSlot { chunk: 0, first_page: 3, pages: 2 };
        assert_eq!(slot.first_face(), 3 * PAGE_FACES);
        assert_eq!(slot.args_offset(), 48);
        assert_eq!(PAGE_BYTES, 256 * 12 + 48);
    }
}
