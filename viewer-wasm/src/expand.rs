//! GPU voxel expansion: one compute dispatch per block turns its PackedVoxel
//! voxels into face records in its run of the face arena
//! ([`crate::face_arena`]), fills that run's page table and counts the
//! indirect draw's vertices (shaders/expand.wgsl). The CPU only sizes the run
//! from the popcount of the face masks ([`Block::face_count`]); a frame's
//! blocks are uploaded with one staging write ([`UploadBatch`]) and expanded
//! in one compute pass, a block a dispatch under one bind group per chunk (its
//! header is a dynamic offset), so a new block creates no WebGPU object.

use bytemuck::{Pod, Zeroable};
use voxstream_format::{BLOCK_SIZE, Block, BlockKey, PackedVoxel};

use crate::face_arena::{BlockSlot, FaceArena, PAGE_INFO_BYTES};
use crate::shaders;

/// Bytes of one face record (shaders: `FaceRecord`).
pub const FACE_RECORD_BYTES: u64 = 12;
/// Invocations per workgroup in expand.wgsl.
const WORKGROUP_SIZE: u32 = 64;

/// A page's entry in its chunk's page table (voxel.wgsl and expand.wgsl: `PageInfo`):
/// where the block that owns the page sits, and where its faces end.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct PageInfo {
    /// Grid-unit position of the block's corner.
    pub origin: [f32; 3],
    /// Voxel edge in grid units.
    pub voxel_size: f32,
    /// One past the block's last face, as an index into the chunk's faces.
    pub face_end: u32,
    pub _pad: [u32; 3],
}

impl PageInfo {
    pub fn for_block(key: &BlockKey, slot: &BlockSlot, faces: u32) -> Self {
        let voxel_size = (1u64 << key.level) as f32;
        Self {
            origin: key.coord().map(|c| c as f32 * BLOCK_SIZE as f32 * voxel_size),
            voxel_size,
            face_end: slot.first_face() + faces,
            _pad: [0; 3],
        }
    }
}

/// What one dispatch of expand.wgsl expands (`ExpandBlock`), read at a dynamic offset.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct ExpandHeader {
    /// Index of the block's first voxel in the upload buffer.
    voxel_first: u32,
    voxel_count: u32,
    first_page: u32,
    pages: u32,
    info: PageInfo,
}

/// Bytes of an [`ExpandHeader`]; the block's initial draw args follow it.
const HEADER_BYTES: u64 = 48;

/// A block living on the GPU, ready to draw with one indirect draw.
pub struct GpuBlock {
    pub key: BlockKey,
    pub faces: u32,
    /// Its run of pages in the face arena.
    pub slot: BlockSlot,
}

/// Layout of group 1 in voxel.wgsl: a chunk's page table and faces.
pub fn block_bind_group_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    let entry = |binding, min| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::VERTEX,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only: true },
            has_dynamic_offset: false,
            min_binding_size: wgpu::BufferSize::new(min),
        },
        count: None,
    };
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("arena draw"),
        entries: &[entry(0, PAGE_INFO_BYTES), entry(1, FACE_RECORD_BYTES)],
    })
}

pub struct Expander {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

/// A compute pass's storage buffer binding; `min` 0: no minimum size.
pub(crate) fn storage_entry(binding: u32, read_only: bool, min: u64) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: wgpu::BufferSize::new(min),
        },
        count: None,
    }
}

impl Expander {
    pub fn new(device: &wgpu::Device) -> Self {
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("expand"),
            entries: &[
                storage_entry(0, true, size_of::<PackedVoxel>() as u64),
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: true,
                        min_binding_size: wgpu::BufferSize::new(HEADER_BYTES),
                    },
                    count: None,
                },
                storage_entry(2, false, FACE_RECORD_BYTES),
                storage_entry(3, false, PAGE_INFO_BYTES),
                storage_entry(4, false, 16),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("expand"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("expand.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::expand_module_source().into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("expand faces"),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some("expand_faces"),
            compilation_options: Default::default(),
            cache: None,
        });
        Self { pipeline, layout }
    }

    /// The expansion's bind group over `upload` and one chunk's (or the primer's) buffers.
    fn group(
        &self,
        device: &wgpu::Device,
        label: &str,
        upload: &wgpu::Buffer,
        [faces, page_table, args]: [&wgpu::Buffer; 3],
    ) -> wgpu::BindGroup {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: upload.as_entire_binding() },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: upload,
                        offset: 0,
                        size: wgpu::BufferSize::new(HEADER_BYTES),
                    }),
                },
                wgpu::BindGroupEntry { binding: 2, resource: faces.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: page_table.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: args.as_entire_binding() },
            ],
        })
    }

    /// Runs the expansion once on nothing (zero workgroups), at startup: the
    /// first use of the pipeline and of its submit path costs the browser's
    /// main thread milliseconds, which would otherwise land on the first frame
    /// that streams blocks in.
    pub fn prime(&self, device: &wgpu::Device, queue: &wgpu::Queue) {
        let buffer = |size: u64, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("expand primer"),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        let storage = wgpu::BufferUsages::STORAGE;
        let upload = buffer(256, storage | wgpu::BufferUsages::UNIFORM);
        let chunk_buffer = |size| buffer(size, storage);
        let (faces, table, args) =
            (chunk_buffer(FACE_RECORD_BYTES), chunk_buffer(PAGE_INFO_BYTES), chunk_buffer(16));
        let group = self.group(device, "expand primer", &upload, [&faces, &table, &args]);
        let mut encoder =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("expand primer") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("expand primer"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &group, &[0]);
            pass.dispatch_workgroups(0, 1, 1);
        }
        queue.submit([encoder.finish()]);
    }

    /// Records one compute pass that expands every block of `batch` (whose
    /// voxels [`UploadBatch::write`] has just written) into its run of `arena`.
    pub fn expand_batch(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        batch: &mut UploadBatch,
        arena: &mut FaceArena,
        upload: &wgpu::Buffer,
        timer: Option<&crate::pass_timer::PassTimer>,
    ) -> Vec<GpuBlock> {
        for item in &batch.items {
            let Some(chunk) = arena.chunk_mut(item.slot.chunk) else { continue };
            // The args (0, 1, 6 × first face, 0) sit after the header in the upload buffer.
            encoder.copy_buffer_to_buffer(
                upload,
                item.header + HEADER_BYTES,
                &chunk.args,
                item.slot.args_offset(),
                16,
            );
            if chunk.expand_group.is_none() {
                chunk.expand_group = Some(self.group(
                    device,
                    "expand chunk",
                    upload,
                    [&chunk.faces, &chunk.page_table, &chunk.args],
                ));
            }
        }
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("expand blocks"),
                timestamp_writes: timer.and_then(|t| t.compute_writes("expand blocks")),
            });
            pass.set_pipeline(&self.pipeline);
            for item in &batch.items {
                let Some(group) = arena.chunk(item.slot.chunk).and_then(|c| c.expand_group.as_ref()) else {
                    continue;
                };
                pass.set_bind_group(0, group, &[item.header as u32]);
                let invocations = item.voxel_count.max(item.slot.pages);
                pass.dispatch_workgroups(invocations.div_ceil(WORKGROUP_SIZE), 1, 1);
            }
        }
        batch.bytes.clear();
        batch
            .items
            .drain(..)
            .map(|item| GpuBlock { key: item.key, faces: item.faces, slot: item.slot })
            .collect()
    }
}

/// Bytes of the upload buffer, and so the per-frame upload cap. A block holds
/// at most 64³ voxels of 12 bytes (3 MiB), so any single block fits.
pub const UPLOAD_BYTES_PER_FRAME: u64 = 4 << 20;
/// The least a paced frame may upload (a block larger than the cap still goes alone).
pub const UPLOAD_PACE_MIN_BYTES: u64 = 64 << 10;

/// Sizes each frame's upload to a main-thread time budget: the cap is the
/// bytes the budget buys at the cost per byte measured on the frames before
/// (packing, the staging write and encoding the expansion, all on the main
/// thread). A fast device gets the whole upload buffer a frame; a slow one (a
/// CPU WebGPU) uploads less a frame and takes more frames, never stalling
/// the page for longer than the budget.
#[derive(Debug, Clone)]
pub struct UploadPacer {
    budget_ms: f64,
    /// Measured cost, smoothed over frames (ms per MiB).
    ms_per_mib: f64,
}

impl UploadPacer {
    /// The cost assumed before the first measurement: a slow device's (a CPU
    /// WebGPU's first upload frame took about 6 ms/MiB), so that the first
    /// upload frame, which also pays for first calls, stays within the
    /// budget. A fast device reaches the whole buffer a few frames later:
    /// each sample halves the estimate's error.
    const FIRST_GUESS_MS_PER_MIB: f64 = 8.0;

    pub fn new(budget_ms: f64) -> Self {
        Self { budget_ms, ms_per_mib: Self::FIRST_GUESS_MS_PER_MIB }
    }

    /// Bytes the next frame may upload, within [`UPLOAD_PACE_MIN_BYTES`, `UPLOAD_BYTES_PER_FRAME`].
    pub fn cap_bytes(&self) -> u64 {
        let bytes = self.budget_ms / self.ms_per_mib * (1u64 << 20) as f64;
        (bytes as u64).clamp(UPLOAD_PACE_MIN_BYTES, UPLOAD_BYTES_PER_FRAME)
    }

    /// Records that uploading `bytes` took `ms` of main thread. Small uploads
    /// are mostly fixed costs and say little about the cost per byte.
    pub fn record(&mut self, bytes: u64, ms: f64) {
        if bytes < UPLOAD_PACE_MIN_BYTES || !ms.is_finite() || ms < 0.0 {
            return;
        }
        let sample = ms / (bytes as f64 / (1u64 << 20) as f64);
        self.ms_per_mib = 0.5 * self.ms_per_mib + 0.5 * sample;
    }
}

/// Uniform binding offsets must be multiples of this (WebGPU's default limit).
const UPLOAD_ALIGN: u64 = 256;

struct UploadItem {
    key: BlockKey,
    faces: u32,
    voxel_count: u32,
    /// Byte offset of the block's [`ExpandHeader`] in the upload buffer.
    header: u64,
    slot: BlockSlot,
}

/// One frame's uploads: every block's voxels, expansion header and draw args
/// packed into one CPU buffer, written to the GPU with one `write_buffer`. Kept from
/// frame to frame ([`Expander::expand_batch`] empties it): its buffer is
/// allocated once, so packing a frame is a copy, never a reallocation.
#[derive(Default)]
pub struct UploadBatch {
    bytes: Vec<u8>,
    items: Vec<UploadItem>,
}

impl UploadBatch {
    /// An empty batch whose buffer already holds a whole frame's upload (so the
    /// first frame that uploads does not grow the wasm heap either).
    pub fn new() -> Self {
        Self { bytes: Vec::with_capacity(UPLOAD_BYTES_PER_FRAME as usize), items: Vec::new() }
    }

    /// The most bytes `block` takes in a batch: its voxels at a multiple of
    /// their size, its header at the next multiple of [`UPLOAD_ALIGN`], the args after it.
    pub fn bytes_for(block: &Block) -> u64 {
        let voxel_bytes = std::mem::size_of_val(block.voxels.as_slice()) as u64;
        size_of::<PackedVoxel>() as u64 - 1 + voxel_bytes + UPLOAD_ALIGN - 1 + HEADER_BYTES + 16
    }

    pub fn len(&self) -> usize {
        self.items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    pub fn byte_len(&self) -> u64 {
        self.bytes.len() as u64
    }

    /// Whether `block` still fits under a frame's cap of `cap` bytes: the
    /// first block always does (any block fits the upload buffer).
    pub fn fits(&self, block: &Block, cap: u64) -> bool {
        self.bytes.is_empty() || self.byte_len() + Self::bytes_for(block) <= cap.min(UPLOAD_BYTES_PER_FRAME)
    }

    /// Adds `block`, which expands to `faces` > 0 faces, to be expanded into `slot`.
    pub fn push(&mut self, block: &Block, faces: u32, slot: BlockSlot) {
        let voxel_size = size_of::<PackedVoxel>();
        self.bytes.resize(self.bytes.len().next_multiple_of(voxel_size), 0);
        let voxel_first = (self.bytes.len() / voxel_size) as u32;
        self.bytes.extend_from_slice(bytemuck::cast_slice(&block.voxels));
        self.bytes.resize(self.bytes.len().next_multiple_of(UPLOAD_ALIGN as usize), 0);
        let header = self.bytes.len() as u64;
        let expand = ExpandHeader {
            voxel_first,
            voxel_count: block.voxels.len() as u32,
            first_page: slot.first_page,
            pages: slot.pages,
            info: PageInfo::for_block(&block.key, &slot, faces),
        };
        self.bytes.extend_from_slice(bytemuck::bytes_of(&expand));
        let args = wgpu::util::DrawIndirectArgs {
            vertex_count: 0,
            instance_count: 1,
            first_vertex: slot.first_face() * 6,
            first_instance: 0,
        };
        self.bytes.extend_from_slice(args.as_bytes());
        self.items.push(UploadItem {
            key: block.key,
            faces,
            voxel_count: block.voxels.len() as u32,
            header,
            slot,
        });
    }

    /// The one staging write of the frame.
    pub fn write(&self, queue: &wgpu::Queue, upload: &wgpu::Buffer) {
        if !self.bytes.is_empty() {
            queue.write_buffer(upload, 0, &self.bytes);
        }
    }
}

/// The buffer every frame's uploads go through.
pub fn upload_buffer(device: &wgpu::Device) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("block uploads"),
        size: UPLOAD_BYTES_PER_FRAME,
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::UNIFORM
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::face_arena::PAGE_FACES;

    #[test]
    fn the_pacer_fits_a_frames_upload_to_its_time_budget() {
        let mut pacer = UploadPacer::new(2.0);
        let first = pacer.cap_bytes();
        assert_eq!(first, 256 << 10, "2 ms at the first guess of 8 ms/MiB");
        // A slower device: 1 MiB took 16 ms. The cap shrinks towards the 2 ms that buy 128 KiB.
        for _ in 0..8 {
            let cap = pacer.cap_bytes();
            pacer.record(cap, 16.0 * cap as f64 / (1u64 << 20) as f64);
        }
        let slow = pacer.cap_bytes();
        assert!((125 << 10..=130 << 10).contains(&slow), "{slow}");
        // A fast device: the whole upload buffer, never more.
        for _ in 0..8 {
            pacer.record(1 << 20, 0.05);
        }
        assert_eq!(pacer.cap_bytes(), UPLOAD_BYTES_PER_FRAME);
        // Control: tiny or broken samples change nothing; a stall still leaves the floor.
        let before = pacer.cap_bytes();
        pacer.record(4096, 50.0);
        pacer.record(1 << 20, f64::NAN);
        assert_eq!(pacer.cap_bytes(), before);
        for _ in 0..8 {
            pacer.record(1 << 20, 1e6);
        }
        assert_eq!(pacer.cap_bytes(), UPLOAD_PACE_MIN_BYTES);
    }

    #[test]
    fn the_first_block_always_fits_a_batch() {
        let key = BlockKey::new(0, 0, 0, 0);
        let big = Block { key, voxels: vec![PackedVoxel::new([1, 1, 1], 1, 0); 100_000] };
        let mut batch = UploadBatch::default();
        assert!(batch.fits(&big, UPLOAD_PACE_MIN_BYTES), "alone, a block larger than the cap goes");
        // As after pushing it (the buffers need a device; the cap only reads the bytes).
        batch.bytes.resize(UploadBatch::bytes_for(&big) as usize, 0);
        let small = Block { key, voxels: vec![PackedVoxel::new([1, 1, 1], 1, 0)] };
        assert!(
            !batch.fits(&small, UPLOAD_PACE_MIN_BYTES),
            "control: a second block waits for the next frame"
        );
        assert!(batch.fits(&small, UPLOAD_BYTES_PER_FRAME));
    }

    #[test]
    fn page_info_places_blocks_in_grid_units() {
        let slot = BlockSlot { chunk: 0, first_page: 2, pages: 1 };
        let u = PageInfo::for_block(&BlockKey::new(2, 1, 0, 3), &slot, 100);
        assert_eq!(u.voxel_size, 4.0);
        assert_eq!(u.origin, [256.0, 0.0, 768.0]);
        assert_eq!(u.face_end, 2 * PAGE_FACES + 100);
        assert_eq!(size_of::<PageInfo>() as u64, PAGE_INFO_BYTES);
        assert_eq!(size_of::<ExpandHeader>() as u64, HEADER_BYTES);
        // expand.wgsl's Voxel and FaceRecord are three u32 each.
        assert_eq!(size_of::<PackedVoxel>(), 12);
        assert_eq!(FACE_RECORD_BYTES, 12);
    }

    #[test]
    fn a_batch_places_voxels_headers_and_args_where_the_shader_reads_them() {
        let key = BlockKey::new(1, 0, 0, 0);
        let mut batch = UploadBatch::default();
        let mut ends = Vec::new();
        for (i, n) in [5usize, 1, 77].into_iter().enumerate() {
            let block = Block { key, voxels: vec![PackedVoxel::new([i as u32, 0, 0], 1, 0); n] };
            let before = batch.byte_len();
            let slot = BlockSlot { chunk: 0, first_page: 10 * i as u32, pages: 1 };
            batch.push(&block, 3, slot);
            assert!(
                batch.byte_len() - before <= UploadBatch::bytes_for(&block),
                "bytes_for is an upper bound"
            );
            ends.push(batch.byte_len());
        }
        for (i, item) in batch.items.iter().enumerate() {
            assert_eq!(item.header % UPLOAD_ALIGN, 0, "a uniform's dynamic offset must be aligned");
            let h = item.header as usize;
            let header: ExpandHeader =
                bytemuck::pod_read_unaligned(&batch.bytes[h..h + HEADER_BYTES as usize]);
            assert_eq!(header.voxel_count, item.voxel_count);
            assert_eq!(header.first_page, 10 * i as u32);
            // The voxels the header points at are the block's own.
            let v = header.voxel_first as usize * 12;
            let first: PackedVoxel = bytemuck::pod_read_unaligned(&batch.bytes[v..v + 12]);
            assert_eq!(first, PackedVoxel::new([i as u32, 0, 0], 1, 0));
            let args: [u32; 4] = bytemuck::pod_read_unaligned(&batch.bytes[h + 48..h + 64]);
            assert_eq!(args, [0, 1, 10 * i as u32 * PAGE_FACES * 6, 0]);
            assert_eq!(h + 64, ends[i] as usize);
        }
    }
}
