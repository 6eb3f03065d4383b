//! GPU memory under a hard byte budget. Every buffer and texture the viewer
//! holds is counted: the frame's fixed targets (colour, depth, occupancy
//! volume, uniforms, the upload buffer) and each block's buffers. Block
//! buffers come from pools of size classes with a free list, so a block that
//! comes back reuses a freed buffer instead of allocating. An allocation that
//! would pass the budget first drops free buffers, then evicts the least
//! recently visible blocks that are not protected (drawn this frame); if it
//! still does not fit it is refused. The budget is never exceeded.
//! No compaction: size classes bound the waste instead (WebGPU cannot copy a
//! buffer onto itself, so compaction would need a second buffer anyway).

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use voxstream_format::BlockKey;

use crate::expand::FACE_RECORD_BYTES;

/// The default budget: 512 MiB.
pub const DEFAULT_BUDGET_BYTES: u64 = 512 << 20;
/// Smallest face-buffer class.
const MIN_CLASS_BYTES: u64 = 4 << 10;
/// Classes per doubling: a buffer wastes at most 1/8 of its size.
const CLASS_STEPS: u64 = 8;
/// A block's draw args and uniform: 16 bytes each.
pub const BLOCK_FIXED_BYTES: u64 = 32;

/// The face-buffer bytes a pool hands out for `bytes`: rounded up to the next
/// of eight steps per power of two (at least [`MIN_CLASS_BYTES`]).
pub fn class_bytes(bytes: u64) -> u64 {
    if bytes <= MIN_CLASS_BYTES {
        return MIN_CLASS_BYTES;
    }
    let octave = 1u64 << (63 - bytes.leading_zeros());
    let step = (octave / CLASS_STEPS).max(1);
    bytes.div_ceil(step) * step
}

/// GPU bytes a resident block of `faces` faces takes.
pub fn block_gpu_bytes(faces: u32) -> u64 {
    class_bytes(faces.max(1) as u64 * FACE_RECORD_BYTES) + BLOCK_FIXED_BYTES
}

/// One block's buffers: faces, indirect draw args, block uniform.
pub struct BlockBuffers {
    pub face_buffer: wgpu::Buffer,
    pub draw_args: wgpu::Buffer,
    pub uniform: wgpu::Buffer,
}

impl BlockBuffers {
    pub fn bytes(&self) -> u64 {
        self.face_buffer.size() + BLOCK_FIXED_BYTES
    }

    fn destroy(&self) {
        self.face_buffer.destroy();
        self.draw_args.destroy();
        self.uniform.destroy();
    }
}

struct Resident {
    bytes: u64,
    last_visible: u64,
}

/// Bookkeeping of GPU bytes. The caller owns the buffers of resident blocks;
/// this decides who may allocate and who must go.
pub struct Residency {
    budget: u64,
    /// Bytes of the frame's own targets and buffers.
    fixed: u64,
    resident: HashMap<BlockKey, Resident>,
    free: HashMap<u64, Vec<BlockBuffers>>,
    free_bytes: u64,
    resident_bytes: u64,
    peak: u64,
}

/// What [`Residency::make_room`] decided.
#[derive(Debug, Default, PartialEq)]
pub struct Room {
    pub fits: bool,
    /// Blocks to drop from the GPU (their buffers go back with [`Residency::release`]).
    pub evict: Vec<BlockKey>,
}

impl Residency {
    pub fn new(budget: u64) -> Self {
        Self {
            budget,
            fixed: 0,
            resident: HashMap::default(),
            free: HashMap::default(),
            free_bytes: 0,
            resident_bytes: 0,
            peak: 0,
        }
    }

    pub fn budget(&self) -> u64 {
        self.budget
    }

    pub fn set_budget(&mut self, budget: u64) {
        self.budget = budget;
    }

    /// Declares the bytes of the fixed targets (they change with the viewport).
    pub fn set_fixed_bytes(&mut self, bytes: u64) {
        self.fixed = bytes;
        self.note_peak();
    }

    pub fn fixed_bytes(&self) -> u64 {
        self.fixed
    }

    /// Everything counted now: fixed, resident blocks and free pool buffers.
    pub fn used_bytes(&self) -> u64 {
        self.fixed + self.resident_bytes + self.free_bytes
    }

    pub fn peak_bytes(&self) -> u64 {
        self.peak
    }

    /// What blocks may take: the budget less the fixed targets.
    pub fn block_budget(&self) -> u64 {
        self.budget.saturating_sub(self.fixed)
    }

    pub fn is_resident(&self, key: &BlockKey) -> bool {
        self.resident.contains_key(key)
    }

    pub fn resident_count(&self) -> usize {
        self.resident.len()
    }

    pub fn mark_visible(&mut self, key: &BlockKey, frame: u64) {
        if let Some(r) = self.resident.get_mut(key) {
            r.last_visible = frame;
        }
    }

    fn note_peak(&mut self) {
        self.peak = self.peak.max(self.used_bytes());
    }

    /// Finds room for `bytes` more: drops free buffers first, then picks the
    /// least recently visible unprotected blocks to evict. The caller must
    /// release every evicted block before allocating.
    pub fn make_room(&mut self, bytes: u64, protected: &HashSet<BlockKey>) -> Room {
        let mut used = self.used_bytes();
        if used + bytes <= self.budget {
            return Room { fits: true, evict: Vec::new() };
        }
        // Free buffers of other sizes are the cheapest to give up.
        for (_, buffers) in self.free.drain() {
            for b in buffers {
                self.free_bytes -= b.bytes();
                used -= b.bytes();
                b.destroy();
            }
        }
        let mut victims: Vec<(u64, BlockKey, u64)> = self
            .resident
            .iter()
            .filter(|(k, _)| !protected.contains(k))
            .map(|(k, r)| (r.last_visible, *k, r.bytes))
            .collect();
        victims.sort();
        let mut evict = Vec::new();
        for (_, key, b) in victims {
            if used + bytes <= self.budget {
                break;
            }
            used -= b;
            evict.push(key);
        }
        Room { fits: used + bytes <= self.budget, evict }
    }

    /// A block left the GPU: its buffers go to the free list (they stay counted).
    pub fn release(&mut self, key: &BlockKey, buffers: BlockBuffers) {
        if let Some(r) = self.resident.remove(key) {
            self.resident_bytes -= r.bytes;
        }
        let bytes = buffers.bytes();
        self.free_bytes += bytes;
        self.free.entry(buffers.face_buffer.size()).or_default().push(buffers);
        // Keep the free list from holding what the budget needs.
        if self.used_bytes() > self.budget {
            self.trim_free();
        }
    }

    fn trim_free(&mut self) {
        for (_, buffers) in self.free.drain() {
            for b in buffers {
                b.destroy();
            }
        }
        self.free_bytes = 0;
    }

    /// Buffers for a block of `faces` faces: a free one of its class, or new
    /// ones. Call [`Residency::make_room`] first; `None` when they would not fit.
    pub fn allocate(
        &mut self,
        device: &wgpu::Device,
        key: BlockKey,
        faces: u32,
        frame: u64,
    ) -> Option<BlockBuffers> {
        let class = class_bytes(faces.max(1) as u64 * FACE_RECORD_BYTES);
        let buffers = match self.free.get_mut(&class).and_then(Vec::pop) {
            Some(b) => {
                self.free_bytes -= b.bytes();
                b
            }
            None => {
                // `make_room` counted its victims as gone, but `release` pools their buffers:
                // other classes are dropped before a new buffer is refused.
                if self.used_bytes() + class + BLOCK_FIXED_BYTES > self.budget {
                    self.trim_free();
                }
                if self.used_bytes() + class + BLOCK_FIXED_BYTES > self.budget {
                    return None;
                }
                new_block_buffers(device, class)
            }
        };
        let bytes = buffers.bytes();
        self.resident_bytes += bytes;
        self.resident.insert(key, Resident { bytes, last_visible: frame });
        self.note_peak();
        Some(buffers)
    }

    /// Drops everything free and forgets every block (their buffers must be destroyed by the caller).
    pub fn clear_free(&mut self) {
        self.trim_free();
    }
}

fn new_block_buffers(device: &wgpu::Device, face_bytes: u64) -> BlockBuffers {
    let face_buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("block faces (pooled)"),
        size: face_bytes,
        // COPY_SRC lets tests read the records back.
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let draw_args = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("block draw args (pooled)"),
        size: 16,
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::INDIRECT
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let uniform = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("block uniform (pooled)"),
        size: 16,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    BlockBuffers { face_buffer, draw_args, uniform }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn classes_round_up_by_at_most_an_eighth() {
        assert_eq!(class_bytes(1), MIN_CLASS_BYTES);
        assert_eq!(class_bytes(MIN_CLASS_BYTES), MIN_CLASS_BYTES);
        for bytes in [4097u64, 10_000, 123_457, 3 << 20, (3 << 20) + 1] {
            let c = class_bytes(bytes);
            assert!(c >= bytes && (c - bytes) * 8 <= c, "{bytes} -> {c}");
            assert_eq!(c % 4, 0, "storage bindings need multiples of 4");
            assert_eq!(class_bytes(c), c, "a class is its own class");
        }
        // Control: a plain power-of-two pool would waste almost half.
        assert!(class_bytes(4097 * 16) < 8192 * 16);
    }

    #[test]
    fn room_evicts_least_recently_visible_unprotected_blocks() {
        let mut r = Residency::new(1000);
        r.set_fixed_bytes(100);
        for (i, frame) in [(0u32, 5u64), (1, 1), (2, 3)] {
            let key = BlockKey::new(0, i, 0, 0);
            r.resident.insert(key, Resident { bytes: 250, last_visible: frame });
            r.resident_bytes += 250;
        }
        assert_eq!(r.used_bytes(), 850);
        assert_eq!(r.make_room(100, &HashSet::default()), Room { fits: true, evict: vec![] });
        // 300 more needs one block out: the one seen longest ago (frame 1).
        let room = r.make_room(300, &HashSet::default());
        assert_eq!(room, Room { fits: true, evict: vec![BlockKey::new(0, 1, 0, 0)] });
        // Protected blocks stay, even if that means no room.
        let all: HashSet<BlockKey> = r.resident.keys().copied().collect();
        assert!(!r.make_room(300, &all).fits);
        // More than the budget can ever hold is refused.
        assert!(!r.make_room(2000, &HashSet::default()).fits);
    }
}
