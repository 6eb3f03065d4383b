//! GPU voxel expansion: one compute dispatch per block turns its PackedVoxel
//! storage buffer into face records and fills the indirect draw args
//! (shaders/expand.wgsl). The CPU only sizes the face buffer from the popcount
//! of the face masks ([`Block::face_count`]); a frame's blocks are uploaded
//! with one staging write ([`UploadBatch`]) and expanded in one compute pass.

use bytemuck::{Pod, Zeroable};
use voxstream_format::{BLOCK_SIZE, Block, BlockKey, PackedVoxel};

use crate::residency::BlockBuffers;
use crate::shaders;

/// Bytes of one face record (shaders: `FaceRecord`).
pub const FACE_RECORD_BYTES: u64 = 12;
/// Invocations per workgroup in expand.wgsl.
const WORKGROUP_SIZE: u32 = 64;

/// Per-block uniform of voxel.wgsl (`BlockInfo`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct BlockUniform {
    /// Grid-unit position of the block's corner.
    pub origin: [f32; 3],
    /// Voxel edge in grid units.
    pub voxel_size: f32,
}

impl BlockUniform {
    pub fn for_key(key: &BlockKey) -> Self {
        let voxel_size = (1u64 << key.level) as f32;
        Self { origin: key.coord().map(|c| c as f32 * BLOCK_SIZE as f32 * voxel_size), voxel_size }
    }
}

/// A block living on the GPU, ready to draw with one indirect draw.
pub struct GpuBlock {
    pub key: BlockKey,
    pub faces: u32,
    /// Pooled buffers (see [`crate::residency`]): face records written by the
    /// compute pass (the first `faces`), indirect draw args, block uniform.
    pub buffers: BlockBuffers,
    /// Group 1 of the draw pipeline: block uniform + face buffer.
    pub bind_group: wgpu::BindGroup,
}

/// Layout of group 1 in voxel.wgsl: what one block's draw reads.
pub fn block_bind_group_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("block draw"),
        entries: &[
            wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: false,
                    min_binding_size: wgpu::BufferSize::new(size_of::<BlockUniform>() as u64),
                },
                count: None,
            },
            wgpu::BindGroupLayoutEntry {
                binding: 1,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: true },
                    has_dynamic_offset: false,
                    min_binding_size: wgpu::BufferSize::new(FACE_RECORD_BYTES),
                },
                count: None,
            },
        ],
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
                storage_entry(1, false, FACE_RECORD_BYTES),
                storage_entry(2, false, 16),
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

    /// Runs the expansion once on nothing (zero workgroups), at startup: the
    /// first use of the pipeline and of its submit path costs the browser's
    /// main thread milliseconds, which would otherwise land on the first frame
    /// that streams blocks in.
    pub fn prime(&self, device: &wgpu::Device, queue: &wgpu::Queue) {
        let buffer = |size: u64| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("expand primer"),
                size,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        };
        let (voxels, faces, args) =
            (buffer(size_of::<PackedVoxel>() as u64), buffer(FACE_RECORD_BYTES), buffer(16));
        let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("expand primer"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: voxels.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: faces.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: args.as_entire_binding() },
            ],
        });
        let mut encoder =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("expand primer") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("expand primer"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(0, 1, 1);
        }
        queue.submit([encoder.finish()]);
    }

    /// Records one compute pass that expands every block of `batch` (whose
    /// voxels [`UploadBatch::finish`] has just written) into its buffers.
    pub fn expand_batch(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        batch: &mut UploadBatch,
        draw_layout: &wgpu::BindGroupLayout,
        upload: &wgpu::Buffer,
        timer: Option<&crate::pass_timer::PassTimer>,
    ) -> Vec<GpuBlock> {
        let mut groups = Vec::with_capacity(batch.items.len());
        for item in &batch.items {
            // Args (0, 1, 0, 0) and the block uniform sit after the voxels in the upload buffer.
            let tail = item.offset + item.voxel_bytes;
            encoder.copy_buffer_to_buffer(upload, tail, &item.buffers.draw_args, 0, 16);
            encoder.copy_buffer_to_buffer(upload, tail + 16, &item.buffers.uniform, 0, 16);
            // Static labels: a formatted one a block costs an allocation and a JS string.
            groups.push(device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("expand block"),
                layout: &self.layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                            buffer: upload,
                            offset: item.offset,
                            size: wgpu::BufferSize::new(item.voxel_bytes),
                        }),
                    },
                    wgpu::BindGroupEntry { binding: 1, resource: face_binding(&item.buffers, item.faces) },
                    wgpu::BindGroupEntry { binding: 2, resource: item.buffers.draw_args.as_entire_binding() },
                ],
            }));
        }
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("expand blocks"),
                timestamp_writes: timer.and_then(|t| t.compute_writes("expand blocks")),
            });
            pass.set_pipeline(&self.pipeline);
            for (item, group) in batch.items.iter().zip(&groups) {
                pass.set_bind_group(0, group, &[]);
                let voxels = (item.voxel_bytes / size_of::<PackedVoxel>() as u64) as u32;
                pass.dispatch_workgroups(voxels.div_ceil(WORKGROUP_SIZE), 1, 1);
            }
        }
        batch.bytes.clear();
        batch
            .items
            .drain(..)
            .map(|item| {
                let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("block draw"),
                    layout: draw_layout,
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: item.buffers.uniform.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 1,
                            resource: face_binding(&item.buffers, item.faces),
                        },
                    ],
                });
                GpuBlock { key: item.key, faces: item.faces, buffers: item.buffers, bind_group }
            })
            .collect()
    }
}

/// The face records of a block: only the first `faces` of its pooled buffer,
/// so `arrayLength` in the shaders is the block's own face count.
fn face_binding(buffers: &BlockBuffers, faces: u32) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer: &buffers.face_buffer,
        offset: 0,
        size: wgpu::BufferSize::new(faces.max(1) as u64 * FACE_RECORD_BYTES),
    })
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

/// Storage-buffer binding offsets must be multiples of this (WebGPU's default limit).
const UPLOAD_ALIGN: u64 = 256;

struct UploadItem {
    key: BlockKey,
    faces: u32,
    offset: u64,
    voxel_bytes: u64,
    buffers: BlockBuffers,
}

/// One frame's uploads: every block's voxels, draw args and uniform packed
/// into one CPU buffer, written to the GPU with one `write_buffer`. Kept from
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

    /// Bytes `block` takes in a batch (with alignment).
    pub fn bytes_for(block: &Block) -> u64 {
        (std::mem::size_of_val(block.voxels.as_slice()) as u64 + 32).next_multiple_of(UPLOAD_ALIGN)
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

    /// Adds `block`, which expands to `faces` > 0 faces, to be expanded into `buffers`.
    pub fn push(&mut self, block: &Block, faces: u32, buffers: BlockBuffers) {
        let offset = self.bytes.len() as u64;
        let voxels: &[u8] = bytemuck::cast_slice(&block.voxels);
        self.bytes.extend_from_slice(voxels);
        let args = wgpu::util::DrawIndirectArgs {
            vertex_count: 0,
            instance_count: 1,
            first_vertex: 0,
            first_instance: 0,
        };
        self.bytes.extend_from_slice(args.as_bytes());
        self.bytes.extend_from_slice(bytemuck::bytes_of(&BlockUniform::for_key(&block.key)));
        self.bytes.resize(self.bytes.len().next_multiple_of(UPLOAD_ALIGN as usize), 0);
        self.items.push(UploadItem {
            key: block.key,
            faces,
            offset,
            voxel_bytes: voxels.len() as u64,
            buffers,
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
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn block_uniform_places_blocks_in_grid_units() {
        let u = BlockUniform::for_key(&BlockKey::new(2, 1, 0, 3));
        assert_eq!(u.voxel_size, 4.0);
        assert_eq!(u.origin, [256.0, 0.0, 768.0]);
        assert_eq!(size_of::<BlockUniform>(), 16);
        // expand.wgsl's Voxel and FaceRecord are three u32 each.
        assert_eq!(size_of::<PackedVoxel>(), 12);
        assert_eq!(FACE_RECORD_BYTES, 12);
    }
}
