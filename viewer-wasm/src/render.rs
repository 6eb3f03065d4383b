//! The draw: one render pass, one indirect draw per block, 6 vertices per face
//! pulled from the face buffer (shaders/voxel.wgsl), depth-tested, into the
//! G-buffer; then the AO's full-screen passes and the composite into the
//! frame's target ([`crate::ao_passes`]), cleared to [`crate::BACKGROUND_RGBA8`].

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3};

use crate::ao::{
    AoSettings, AoStructure, AoUniform, OccupancyTexture, OccupancyVolume, cells_for_grid, volume_cell,
};
use crate::ao_passes::AoPasses;
pub use crate::ao_passes::{GBUFFER_COLOUR_FORMAT, GBUFFER_NORMAL_FORMAT, GBUFFER_POSITION_FORMAT};
use crate::clipmap::{CLIP_CELLS, ClipmapLayout, OccupancyClipmap};
use crate::crossfade::{FADE_SLOT_BYTES, Fade, MAX_FADES};
use crate::expand::{Expander, GpuBlock, block_bind_group_layout};
use crate::face_arena::FaceArena;
use crate::shaders;

pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// Group 0 uniform of voxel.wgsl (`Frame`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct FrameUniform {
    pub view_proj: [f32; 16],
    pub eye: [f32; 4],
    pub key_light: [f32; 4],
    /// Grid edge (grid units), grid edge / finest occupancy cell, occupancy
    /// mips or clipmap levels, AO strength.
    pub volume: [f32; 4],
    /// `ao_cone`, `ao_range`, `ao_dirs` (this frame's jittered cone set).
    pub ao: AoUniform,
    /// The previous frame's view_proj (temporal reprojection).
    pub prev_view_proj: [f32; 16],
    /// Trace downscale, traced pixel offset x and y, 1 = bilateral upsampling.
    pub ao_sparse: [f32; 4],
    /// Frames averaged (N), history valid, reject disoccluded history, interleaved sampling.
    pub ao_temporal: [f32; 4],
    /// x: 1 = the AO field mode (G-buffer V where the voxel has a field),
    /// y: this frame's step phase ([`crate::ao::ConeJitter`]), z: 1 = jitter
    /// the first step along each cone, w: 0.
    pub ao_mode: [f32; 4],
}

/// What one frame is drawn with.
#[derive(Debug, Clone, Copy)]
pub struct FrameParams {
    pub view_proj: Mat4,
    pub eye: Vec3,
    /// Grid units per grid edge (the scene grid resolution).
    pub grid_resolution: f32,
    /// 0 disables ambient occlusion.
    pub ao_strength: f32,
}

/// The sRGB-free clear colour of [`crate::BACKGROUND_RGBA8`].
pub fn background_color() -> wgpu::Color {
    let [r, g, b, a] = crate::BACKGROUND_RGBA8.map(|c| c as f64 / 255.0);
    wgpu::Color { r, g, b, a }
}

struct DepthTarget {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    size: (u32, u32),
}

pub struct Renderer {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub color_format: wgpu::TextureFormat,
    pub expander: Expander,
    pub block_layout: wgpu::BindGroupLayout,
    /// The voxel draw into the G-buffer (`fs_gbuffer`).
    pipeline: wgpu::RenderPipeline,
    frame_uniform: wgpu::Buffer,
    frame_layout: wgpu::BindGroupLayout,
    frame_group: wgpu::BindGroup,
    occupancy: OccupancyTexture,
    /// The AO's multi-resolution structure (the default); `occupancy` is the volume.
    pub clipmap: OccupancyClipmap,
    depth: Option<DepthTarget>,
    /// The cone tracer's settings, read at every frame.
    pub ao: AoSettings,
    /// The G-buffer, the AO passes and their history.
    pub ao_passes: AoPasses,
    /// `fs_fade` with group 2: one uniform slot per fading block (dynamic offset).
    fade_pipeline: wgpu::RenderPipeline,
    fade_buffer: wgpu::Buffer,
    fade_group: wgpu::BindGroup,
    /// GPU time per pass, where the device has timestamp queries (native).
    pub pass_timer: Option<crate::pass_timer::PassTimer>,
}

/// GPU bytes of the cross-fade slots.
pub const FADE_BUFFER_BYTES: u64 = MAX_FADES as u64 * FADE_SLOT_BYTES;

impl Renderer {
    /// Builds the pipelines for colour targets of `color_format` and the AO's
    /// structures for a `grid_resolution`³ scene: an occupancy volume of
    /// [`cells_for_grid`]³ and a clipmap of [`CLIP_CELLS`]³ levels.
    pub fn new(
        device: wgpu::Device,
        queue: wgpu::Queue,
        color_format: wgpu::TextureFormat,
        grid_resolution: u32,
    ) -> Self {
        let occupancy_cells = cells_for_grid(grid_resolution);
        let expander = Expander::new(&device);
        expander.prime(&device, &queue);
        let block_layout = block_bind_group_layout(&device);
        // Compute too: the AO's trace, upsample and temporal passes bind the frame.
        let visible = wgpu::ShaderStages::FRAGMENT.union(wgpu::ShaderStages::COMPUTE);
        let [occupancy, occupancy_sampler] = filtered_3d_entries(1, visible);
        // The clipmap's texels and their sampler: only the trace reads them.
        let [clip_texels, clip_sampler] = filtered_3d_entries(4, wgpu::ShaderStages::COMPUTE);
        let frame_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("frame"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::VERTEX_FRAGMENT.union(wgpu::ShaderStages::COMPUTE),
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: wgpu::BufferSize::new(size_of::<FrameUniform>() as u64),
                    },
                    count: None,
                },
                occupancy,
                occupancy_sampler,
                wgpu::BindGroupLayoutEntry {
                    binding: 3,
                    visibility: visible,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: wgpu::BufferSize::new(
                            size_of::<crate::clipmap::ClipmapUniform>() as u64
                        ),
                    },
                    count: None,
                },
                clip_texels,
                clip_sampler,
            ],
        });
        let frame_uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("frame"),
            size: size_of::<FrameUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let occupancy = OccupancyTexture::new(&device, occupancy_cells);
        let mut clipmap = OccupancyClipmap::new(&device, CLIP_CELLS);
        // The AO's default structure: its cells are allocated here, before
        // the first block streams in, not in a frame.
        clipmap.reserve(&device, grid_resolution);
        let frame_group = frame_bind_group(&device, &frame_layout, &frame_uniform, &occupancy, &clipmap);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("voxel.wgsl + ao.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::voxel_module_source().into()),
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("voxel draw"),
            bind_group_layouts: &[Some(&frame_layout), Some(&block_layout)],
            immediate_size: 0,
        });
        let gbuffer_targets = [
            Some(GBUFFER_POSITION_FORMAT.into()),
            Some(GBUFFER_NORMAL_FORMAT.into()),
            Some(GBUFFER_COLOUR_FORMAT.into()),
        ];
        let pipeline = voxel_pipeline(&device, &module, &layout, &gbuffer_targets, "fs_gbuffer");
        let ao_passes = AoPasses::new(&device, &frame_layout, color_format);
        let fade_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("fade"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: wgpu::BufferSize::new(16),
                },
                count: None,
            }],
        });
        let fade_buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("fade slots"),
            size: FADE_BUFFER_BYTES,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let fade_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("fade"),
            layout: &fade_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &fade_buffer,
                    offset: 0,
                    size: wgpu::BufferSize::new(16),
                }),
            }],
        });
        let fade_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("voxel draw, fading"),
            bind_group_layouts: &[Some(&frame_layout), Some(&block_layout), Some(&fade_layout)],
            immediate_size: 0,
        });
        let fade_pipeline = voxel_pipeline(&device, &module, &fade_layout, &gbuffer_targets, "fs_fade");
        let pass_timer = crate::pass_timer::PassTimer::new(&device, &queue);
        Self {
            device,
            queue,
            color_format,
            expander,
            block_layout,
            pipeline,
            frame_uniform,
            frame_layout,
            frame_group,
            occupancy,
            clipmap,
            depth: None,
            ao: AoSettings::default(),
            ao_passes,
            fade_pipeline,
            fade_buffer,
            fade_group,
            pass_timer,
        }
    }

    /// Whether the view's AO is still accumulating frames (draw again even without input).
    pub fn ao_accumulating(&self) -> bool {
        self.ao_passes.accumulating()
    }
}

/// A filterable 3D texture at `binding` and its filtering sampler at the next binding.
fn filtered_3d_entries(binding: u32, visibility: wgpu::ShaderStages) -> [wgpu::BindGroupLayoutEntry; 2] {
    [
        wgpu::BindGroupLayoutEntry {
            binding,
            visibility,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: true },
                view_dimension: wgpu::TextureViewDimension::D3,
                multisampled: false,
            },
            count: None,
        },
        wgpu::BindGroupLayoutEntry {
            binding: binding + 1,
            visibility,
            ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
            count: None,
        },
    ]
}

fn frame_bind_group(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    uniform: &wgpu::Buffer,
    occupancy: &OccupancyTexture,
    clipmap: &OccupancyClipmap,
) -> wgpu::BindGroup {
    let entries = [
        wgpu::BindGroupEntry { binding: 0, resource: uniform.as_entire_binding() },
        wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::TextureView(&occupancy.view) },
        wgpu::BindGroupEntry { binding: 2, resource: wgpu::BindingResource::Sampler(&occupancy.sampler) },
        wgpu::BindGroupEntry { binding: 3, resource: clipmap.uniform_buffer.as_entire_binding() },
        wgpu::BindGroupEntry {
            binding: 4,
            resource: wgpu::BindingResource::TextureView(clipmap.texel_view()),
        },
        wgpu::BindGroupEntry { binding: 5, resource: wgpu::BindingResource::Sampler(&clipmap.texel_sampler) },
    ];
    device.create_bind_group(&wgpu::BindGroupDescriptor { label: Some("frame"), layout, entries: &entries })
}

fn attachment(view: &wgpu::TextureView, clear: wgpu::Color) -> Option<wgpu::RenderPassColorAttachment<'_>> {
    Some(wgpu::RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations { load: wgpu::LoadOp::Clear(clear), store: wgpu::StoreOp::Store },
    })
}

fn voxel_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    layout: &wgpu::PipelineLayout,
    targets: &[Option<wgpu::ColorTargetState>],
    fragment: &str,
) -> wgpu::RenderPipeline {
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("voxel draw"),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some("vs_main"),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: wgpu::PrimitiveState {
            topology: wgpu::PrimitiveTopology::TriangleList,
            front_face: wgpu::FrontFace::Ccw,
            // Exposed faces bound closed shells, so back faces are always hidden.
            cull_mode: Some(wgpu::Face::Back),
            ..Default::default()
        },
        depth_stencil: Some(wgpu::DepthStencilState {
            format: DEPTH_FORMAT,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::Less),
            stencil: Default::default(),
            bias: Default::default(),
        }),
        multisample: Default::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(fragment),
            compilation_options: Default::default(),
            targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

impl Renderer {
    /// The depth target of the last frame (for occlusion feedback).
    pub fn depth_texture(&self) -> Option<&wgpu::Texture> {
        self.depth.as_ref().map(|d| &d.texture)
    }

    pub fn occupancy_cells(&self) -> u32 {
        self.occupancy.cells
    }

    pub fn upload_occupancy(&self, volume: &OccupancyVolume) {
        self.occupancy.upload(&self.queue, volume);
    }

    /// Brings the clipmap up to date (see [`OccupancyClipmap::update`]): only
    /// what changed since the last call is cleared and splatted, by compute
    /// passes recorded into `encoder` (the caller's frame submits them).
    pub fn update_clipmap<'a>(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        grid_resolution: u32,
        layout: ClipmapLayout,
        view: (glam::Vec3, glam::Vec3),
        sources: &[Vec<voxstream_format::BlockKey>],
        block: impl Fn(&voxstream_format::BlockKey) -> Option<&'a voxstream_format::Block>,
    ) {
        let (eye, forward) = view;
        let replaced = self.clipmap.update(
            &self.device,
            &self.queue,
            encoder,
            grid_resolution,
            layout,
            eye,
            forward,
            sources,
            block,
            self.pass_timer.as_ref(),
        );
        if replaced {
            self.frame_group = frame_bind_group(
                &self.device,
                &self.frame_layout,
                &self.frame_uniform,
                &self.occupancy,
                &self.clipmap,
            );
        }
    }

    /// Whether the AO traces the clipmap this frame (its setting, once the clipmap has been built).
    pub fn traces_clipmap(&self) -> bool {
        self.ao.structure == AoStructure::Clipmap && self.clipmap.layout().is_some()
    }

    fn depth_view(&mut self, width: u32, height: u32) -> &wgpu::TextureView {
        if self.depth.as_ref().is_none_or(|d| d.size != (width, height)) {
            let texture = self.device.create_texture(&wgpu::TextureDescriptor {
                label: Some("depth"),
                size: wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: DEPTH_FORMAT,
                // Occlusion feedback reduces the depth (TEXTURE_BINDING) and reads it back,
                // whole for a pick (COPY_SRC) (occlusion.rs).
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::COPY_SRC
                    | wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            });
            let view = texture.create_view(&Default::default());
            self.depth = Some(DepthTarget { texture, view, size: (width, height) });
        }
        &self.depth.as_ref().expect("just created").view
    }

    /// Records the frame into `encoder`: the G-buffer cleared, one indirect
    /// draw per block, then the AO passes and the composite into `target`.
    pub fn encode_frame(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        size: (u32, u32),
        params: &FrameParams,
        arena: &FaceArena,
        blocks: &[(&GpuBlock, Option<Fade>)],
    ) {
        // A key light from above and to the side of the viewer; the headlight is implicit.
        let key_light = (Vec3::new(0.4, 1.0, 0.3)).normalize();
        let (width, height) = (size.0.max(1), size.1.max(1));
        let ao_on = params.ao_strength > 0.0;
        let settings = ao_on.then_some(self.ao);
        self.ao_passes.targets(&self.device, (width, height), if ao_on { self.ao.downscale() } else { 1 });
        let state = self.ao_passes.begin_frame(settings.as_ref());
        let jitter = self.ao.jitter_for_frame(state.index);
        let clipmap = self.traces_clipmap();
        // The structure traced: its finest cell (grid units) and level (mip) count.
        let (finest_cell, lods) = match self.clipmap.layout().filter(|_| clipmap) {
            Some(l) => (l.finest_cell as f32, l.levels as f32),
            None => (volume_cell(params.grid_resolution as u32), self.occupancy.mip_count() as f32),
        };
        self.queue.write_buffer(
            &self.clipmap.uniform_buffer,
            0,
            bytemuck::bytes_of(&self.clipmap.uniform(clipmap)),
        );
        let uniform = FrameUniform {
            view_proj: params.view_proj.to_cols_array(),
            eye: params.eye.extend(1.0).to_array(),
            key_light: key_light.extend(0.0).to_array(),
            volume: [params.grid_resolution, params.grid_resolution / finest_cell, lods, params.ao_strength],
            ao: self.ao.uniform_jittered(params.grid_resolution as u32, finest_cell, jitter),
            prev_view_proj: state.prev_view_proj.to_cols_array(),
            ao_sparse: state.sparse,
            ao_temporal: state.temporal,
            ao_mode: [
                if self.ao.mode == crate::ao::AoMode::Field { 1.0 } else { 0.0 },
                jitter.step_phase as f32,
                if self.ao.jitter { 1.0 } else { 0.0 },
                0.0,
            ],
        };
        self.queue.write_buffer(&self.frame_uniform, 0, bytemuck::bytes_of(&uniform));
        let depth = self.depth_view(width, height).clone();
        let [position, normal, colour] = self.ao_passes.gbuffer_views();
        self.encode_voxels(encoder, &depth, [&position, &normal, &colour], arena, blocks);
        self.ao_passes.encode(
            &self.device,
            encoder,
            &self.frame_group,
            settings.as_ref(),
            target,
            params.view_proj,
            self.pass_timer.as_ref(),
        );
    }

    /// The voxel draw into the G-buffer: the blocks not fading, then the fading ones through `fs_fade`.
    fn encode_voxels(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        depth: &wgpu::TextureView,
        [position, normal, colour]: [&wgpu::TextureView; 3],
        arena: &FaceArena,
        blocks: &[(&GpuBlock, Option<Fade>)],
    ) {
        let attachments = [
            attachment(position, wgpu::Color::TRANSPARENT),
            attachment(normal, wgpu::Color::TRANSPARENT),
            attachment(colour, background_color()),
        ];
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("voxels"),
            color_attachments: &attachments,
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: depth,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    // Kept for the occlusion feedback's readback.
                    store: wgpu::StoreOp::Store,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: self.pass_timer.as_ref().and_then(|t| t.render_writes("voxels")),
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.frame_group, &[]);
        // A chunk's group is set once for the blocks after it that share it.
        let mut bound = None;
        for (block, _) in blocks.iter().filter(|(_, fade)| fade.is_none()) {
            let Some(chunk) = arena.chunk(block.slot.chunk) else { continue };
            if bound != Some(block.slot.chunk) {
                pass.set_bind_group(1, &chunk.draw_group, &[]);
                bound = Some(block.slot.chunk);
            }
            pass.draw_indirect(&chunk.args, block.slot.args_offset());
        }
        let fading: Vec<(&GpuBlock, Fade)> =
            blocks.iter().filter_map(|(b, f)| f.map(|f| (*b, f))).take(MAX_FADES).collect();
        if fading.is_empty() {
            return;
        }
        let mut slots = vec![0u8; fading.len() * FADE_SLOT_BYTES as usize];
        for (i, (_, f)) in fading.iter().enumerate() {
            let value = [f.t, if f.incoming { 1.0 } else { 0.0 }, 0.0, 0.0];
            slots[i * FADE_SLOT_BYTES as usize..][..16].copy_from_slice(bytemuck::cast_slice(&value));
        }
        self.queue.write_buffer(&self.fade_buffer, 0, &slots);
        pass.set_pipeline(&self.fade_pipeline);
        for (i, (block, _)) in fading.iter().enumerate() {
            let Some(chunk) = arena.chunk(block.slot.chunk) else { continue };
            pass.set_bind_group(1, &chunk.draw_group, &[]);
            pass.set_bind_group(2, &self.fade_group, &[(i as u64 * FADE_SLOT_BYTES) as u32]);
            pass.draw_indirect(&chunk.args, block.slot.args_offset());
        }
    }
}
