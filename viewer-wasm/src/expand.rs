//! GPU voxel expansion: one compute dispatch per block turns its PackedVoxel
//! storage buffer into face records and fills the indirect draw args
//! (shaders/expand.wgsl). The CPU only sizes the face buffer, exactly, from the
//! popcount of the face masks ([`Block::face_count`]).

use bytemuck::{Pod, Zeroable};
use voxstream_format::{BLOCK_SIZE, Block, BlockKey, PackedVoxel};
use wgpu::util::DeviceExt;

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
    /// Face records written by the compute pass (vertex-pulled by the draw).
    pub face_buffer: wgpu::Buffer,
    /// `DrawIndirectArgs`, vertex count filled in by the compute pass.
    pub draw_args: wgpu::Buffer,
    /// Group 1 of the draw pipeline: block uniform + face buffer.
    pub bind_group: wgpu::BindGroup,
    pub gpu_bytes: u64,
}

impl GpuBlock {
    /// Frees the GPU memory now rather than whenever the handles are collected.
    pub fn destroy(&self) {
        self.face_buffer.destroy();
        self.draw_args.destroy();
    }
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

fn storage_entry(binding: u32, read_only: bool, min: u64) -> wgpu::BindGroupLayoutEntry {
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

    /// Uploads `block`'s voxels and records the compute pass that expands them
    /// into `encoder`. Returns `None` for a block without faces (nothing to draw).
    /// The voxel buffer is only needed by this pass and is released with it.
    pub fn expand(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        block: &Block,
        draw_layout: &wgpu::BindGroupLayout,
    ) -> Option<GpuBlock> {
        let faces = block.face_count();
        if faces == 0 || block.voxels.is_empty() {
            return None;
        }
        let label = format!("block {}", block.key);
        let voxel_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&label),
            contents: bytemuck::cast_slice(&block.voxels),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let face_bytes = faces as u64 * FACE_RECORD_BYTES;
        let face_buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(&label),
            size: face_bytes,
            // COPY_SRC lets tests read the records back.
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let draw_args = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&label),
            contents: wgpu::util::DrawIndirectArgs {
                vertex_count: 0,
                instance_count: 1,
                first_vertex: 0,
                first_instance: 0,
            }
            .as_bytes(),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::INDIRECT | wgpu::BufferUsages::COPY_SRC,
        });
        let expand_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(&label),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: voxel_buffer.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: face_buffer.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: draw_args.as_entire_binding() },
            ],
        });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(&label),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &expand_group, &[]);
            pass.dispatch_workgroups((block.voxels.len() as u32).div_ceil(WORKGROUP_SIZE), 1, 1);
        }
        let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&label),
            contents: bytemuck::bytes_of(&BlockUniform::for_key(&block.key)),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(&label),
            layout: draw_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: uniform.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: face_buffer.as_entire_binding() },
            ],
        });
        Some(GpuBlock {
            key: block.key,
            faces,
            face_buffer,
            draw_args,
            bind_group,
            gpu_bytes: face_bytes + 16 + 16,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
