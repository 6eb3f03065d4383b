//! The frame's targets and the AO's full-screen passes after the voxel draw,
//! one shader a pass (seed 001 §1.1: deferred, sparse, upsampled):
//!
//! 1. the voxel draw (render.rs, voxel.wgsl) writes the G-buffer: grid
//!    position, normal, lit colour without AO, depth;
//! 2. **trace** (ao_trace.wgsl + ao.wgsl): cone tracing for one pixel of each
//!    f×f block into a 1/f-resolution target (f = 1, 2 or 4);
//! 3. **upsample** (ao_upsample.wgsl, f > 1 only): joint bilateral upsampling
//!    to full resolution, guided by the G-buffer's position and normal; it
//!    queues the pixels no traced texel matches, and **retrace**
//!    (ao_retrace.wgsl, dispatched indirectly from the queue) traces them;
//! 4. **temporal** (ao_temporal.wgsl, N > 1 only): the history reprojected
//!    with the previous frame's view-projection, dropped where position or
//!    normal disagree, blended with weight max(1/frames, 1/N);
//! 5. **composite** (ao_composite.wgsl): colour × V into the frame's target.
//!
//! Passes 2–4 are compute passes writing storage textures (8×8 workgroups, a
//! texel an invocation); only the composite, which writes the frame's target,
//! is a full-screen triangle. Why: a GPU with few raster units (a data-centre
//! H100 shades fragments on 2 of its 66 TPCs) ran the fragment trace 30–70×
//! slower than it runs in compute; on other GPUs the two cost about the same.
//!
//! With jitter on, each frame turns the cone set about the normal
//! ([`crate::ao::ConeJitter`]) and moves the traced pixel within its block
//! ([`crate::ao::traced_pixel_offset`]), so accumulated frames average
//! different cone sets and pixels. Position, normal and history are
//! ping-ponged: a frame reads the previous frame's pair.

use std::cell::RefCell;

use glam::Mat4;
use rustc_hash::FxHashMap as HashMap;

use crate::ao::{AoSettings, Upsample, traced_pixel_offset};
use crate::shaders::AoPass;

/// The G-buffer's position target (xyz grid units, w 1).
pub const GBUFFER_POSITION_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;
/// The G-buffer's normal target (xyz unit normal, w 1 on a surface, 0 on the background).
pub const GBUFFER_NORMAL_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
/// The G-buffer's colour target: lit, AO not applied.
pub const GBUFFER_COLOUR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// The traced (1/f resolution) and upsampled visibility: V in r.
pub const VISIBILITY_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Float;
/// The temporal history: (V, frames accumulated, 0, 1).
pub const HISTORY_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;

/// GPU bytes of the targets at a viewport size and downscale (residency).
pub fn target_bytes(width: u32, height: u32, downscale: u32) -> u64 {
    let pixels = width as u64 * height as u64;
    let f = downscale.max(1);
    let low = width.div_ceil(f) as u64 * height.div_ceil(f) as u64;
    // Position ×2, normal ×2, colour, upsampled V, history ×2; traced V; the retrace queue.
    pixels * (16 * 2 + 8 * 2 + 4 + 4 + 16 * 2) + low * 4 + retrace_queue_bytes((width, height))
}

/// The retrace queue's header: count, then the indirect dispatch's three
/// workgroup counts (ao_upsample.wgsl `RetraceQueue`).
const RETRACE_HEADER: u64 = 16;
/// Where the indirect dispatch's arguments start in the queue.
const RETRACE_DISPATCH_OFFSET: u64 = 4;
/// Workgroup size of the retrace pass (ao_retrace.wgsl), and how many queued
/// pixels the upsample counts a workgroup for (ao_upsample.wgsl).
const RETRACE_WORKGROUP: u32 = 64;

/// Bytes of the retrace queue: room for one pixel in 8 (an image whose
/// edges need more traces the rest in the upsample pass itself).
fn retrace_queue_bytes((width, height): (u32, u32)) -> u64 {
    let slots = (width as u64 * height as u64).div_ceil(8).max(RETRACE_WORKGROUP as u64);
    RETRACE_HEADER + 4 * slots
}

/// Every texture a frame draws into, at the viewport size.
pub struct FrameTargets {
    pub size: (u32, u32),
    pub downscale: u32,
    pub position: [wgpu::Texture; 2],
    pub normal: [wgpu::Texture; 2],
    pub colour: wgpu::Texture,
    /// V at 1/downscale resolution (full resolution when downscale is 1).
    pub traced: wgpu::Texture,
    /// V upsampled to full resolution.
    pub upsampled: wgpu::Texture,
    pub history: [wgpu::Texture; 2],
    /// The pixels the upsample could not match, for the retrace pass: a
    /// count, the indirect dispatch's arguments, the packed pixels.
    retrace_queue: wgpu::Buffer,
    views: TargetViews,
    /// The passes' input bind groups, made on first use and kept as long as
    /// the targets: a frame then creates no view and no bind group (each is a
    /// call into the browser's WebGPU, on the main thread).
    groups: RefCell<HashMap<InputsKey, wgpu::BindGroup>>,
}

/// A view of each of [`FrameTargets`]' textures, made with them.
struct TargetViews {
    position: [wgpu::TextureView; 2],
    normal: [wgpu::TextureView; 2],
    colour: wgpu::TextureView,
    traced: wgpu::TextureView,
    upsampled: wgpu::TextureView,
    history: [wgpu::TextureView; 2],
}

/// What a pass's inputs are ([`FrameTargets::inputs`]): the pass, the pair
/// written this frame, and the V texture the temporal or composite pass reads.
type InputsKey = (AoPass, usize, Option<VisibilityTexture>);

impl FrameTargets {
    fn new(device: &wgpu::Device, size: (u32, u32), downscale: u32) -> Self {
        let make = |label: &str, format, (width, height): (u32, u32)| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                // COPY_SRC: `voxstream render` and the tests read them back.
                // STORAGE_BINDING: the compute passes' outputs, V and the history (the
                // positions share the history's format, so they get it too: unused).
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC
                    | if format == VISIBILITY_FORMAT || format == HISTORY_FORMAT {
                        wgpu::TextureUsages::STORAGE_BINDING
                    } else {
                        wgpu::TextureUsages::empty()
                    },
                view_formats: &[],
            })
        };
        let low = (size.0.div_ceil(downscale), size.1.div_ceil(downscale));
        let position = [
            make("g-buffer position a", GBUFFER_POSITION_FORMAT, size),
            make("g-buffer position b", GBUFFER_POSITION_FORMAT, size),
        ];
        let normal = [
            make("g-buffer normal a", GBUFFER_NORMAL_FORMAT, size),
            make("g-buffer normal b", GBUFFER_NORMAL_FORMAT, size),
        ];
        let colour = make("g-buffer colour", GBUFFER_COLOUR_FORMAT, size);
        let traced = make("ao traced", VISIBILITY_FORMAT, low);
        let upsampled = make("ao upsampled", VISIBILITY_FORMAT, size);
        let history =
            [make("ao history a", HISTORY_FORMAT, size), make("ao history b", HISTORY_FORMAT, size)];
        let retrace_queue = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("ao retrace queue"),
            size: retrace_queue_bytes(size),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::INDIRECT | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: true,
        });
        // The dispatch's y and z stay 1; each frame clears count and x.
        retrace_queue
            .slice(..RETRACE_HEADER)
            .get_mapped_range_mut()
            .expect("a buffer mapped at creation maps")
            .copy_from_slice(bytemuck::cast_slice(&[0u32, 0, 1, 1]));
        retrace_queue.unmap();
        let view = |t: &wgpu::Texture| t.create_view(&Default::default());
        let views = TargetViews {
            position: position.each_ref().map(view),
            normal: normal.each_ref().map(view),
            colour: view(&colour),
            traced: view(&traced),
            upsampled: view(&upsampled),
            history: history.each_ref().map(view),
        };
        Self {
            size,
            downscale,
            position,
            normal,
            colour,
            traced,
            upsampled,
            history,
            retrace_queue,
            views,
            groups: RefCell::default(),
        }
    }

    fn visibility_view(&self, v: Option<VisibilityTexture>) -> &wgpu::TextureView {
        match v {
            Some(VisibilityTexture::History(i)) => &self.views.history[i],
            Some(VisibilityTexture::Upsampled) => &self.views.upsampled,
            _ => &self.views.traced,
        }
    }

    /// A pass's bindings, in binding order, from its key: `pair` the position
    /// and normal written this frame, `visibility` the V it reads (Temporal,
    /// Composite), then a compute pass's output, then the upsample's queue.
    /// The key is the bind group cache's, so it must name every binding.
    fn inputs(&self, (pass, pair, visibility): InputsKey) -> Vec<wgpu::BindingResource<'_>> {
        let v = &self.views;
        let prev = 1 - pair;
        let queue = || self.retrace_queue.as_entire_binding();
        let views = match pass {
            AoPass::Trace => vec![&v.position[pair], &v.normal[pair], &v.traced],
            AoPass::Upsample => {
                let mut r: Vec<_> = [&v.position[pair], &v.normal[pair], &v.traced, &v.upsampled]
                    .map(wgpu::BindingResource::TextureView)
                    .into();
                r.push(queue());
                return r;
            }
            AoPass::Retrace => {
                let [p, n, out] = [&v.position[pair], &v.normal[pair], &v.upsampled]
                    .map(wgpu::BindingResource::TextureView);
                return vec![p, n, queue(), out];
            }
            AoPass::Temporal => vec![
                &v.position[pair],
                &v.normal[pair],
                self.visibility_view(visibility),
                &v.position[prev],
                &v.normal[prev],
                &v.history[prev],
                &v.history[pair],
            ],
            AoPass::Composite => vec![&v.normal[pair], &v.colour, self.visibility_view(visibility)],
        };
        views.into_iter().map(wgpu::BindingResource::TextureView).collect()
    }
}

/// Where the last frame's final V is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum VisibilityTexture {
    /// `traced` (downscale 1, no accumulation): V in r of an R32Float texture.
    Traced,
    /// `upsampled` (downscale > 1, no accumulation).
    Upsampled,
    /// `history[i]`: V in r of an Rgba32Float texture, frames in g.
    History(usize),
}

/// What the last frame left in the targets.
pub struct LastFrame<'a> {
    pub position: &'a wgpu::Texture,
    pub normal: &'a wgpu::Texture,
    /// The final V (in the first f32 of each texel) and the bytes of a texel;
    /// `None` with AO off.
    pub visibility: Option<(&'a wgpu::Texture, u32)>,
}

/// The uniform values the AO passes read beside the settings.
#[derive(Debug, Clone, Copy)]
pub struct AoFrameState {
    pub prev_view_proj: Mat4,
    pub sparse: [f32; 4],
    pub temporal: [f32; 4],
    /// Frame index in the accumulation: the jitter of the cone set.
    pub index: u32,
}

/// A pass's pipeline: compute, or the composite's full-screen triangle.
enum PassPipeline {
    Compute(wgpu::ComputePipeline),
    Render(wgpu::RenderPipeline),
}

/// The AO passes' pipelines, the targets and the history's state.
pub struct AoPasses {
    pipelines: Vec<(AoPass, PassPipeline, wgpu::BindGroupLayout)>,
    targets: Option<FrameTargets>,
    /// The pair (position, normal, history) the next frame writes.
    current: usize,
    /// Frames since the history was reset: the jitter index.
    frame_index: u32,
    /// Frames drawn with the current view unchanged (pixels disoccluded while
    /// the camera moved have that many frames in their history at least).
    still_frames: u32,
    /// The pair not written next holds a usable previous frame.
    history_valid: bool,
    prev_view_proj: Mat4,
    /// The settings of the last frame (a change resets the history).
    last_settings: Option<AoSettings>,
    /// The last frame's final V, if it ran the AO.
    last_visibility: Option<VisibilityTexture>,
    /// Accumulating: the last frame ran the temporal pass with fewer than N frames in.
    accumulating: bool,
}

fn texture_entry(binding: u32, visibility: wgpu::ShaderStages) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Float { filterable: false },
            view_dimension: wgpu::TextureViewDimension::D2,
            multisampled: false,
        },
        count: None,
    }
}

/// Textures group 1 of each pass reads (all with textureLoad).
fn pass_texture_count(pass: AoPass) -> u32 {
    match pass {
        AoPass::Trace | AoPass::Retrace => 2,
        AoPass::Upsample => 3,
        AoPass::Temporal => 6,
        AoPass::Composite => 3,
    }
}

/// Group 1 of a pass: its textures, the retrace pass's queue (read), the
/// storage texture a compute pass writes, the upsample's queue (written).
fn pass_layout_entries(pass: AoPass, stage: wgpu::ShaderStages) -> Vec<wgpu::BindGroupLayoutEntry> {
    let inputs = pass_texture_count(pass);
    let mut entries: Vec<_> = (0..inputs).map(|b| texture_entry(b, stage)).collect();
    if pass == AoPass::Retrace {
        entries.push(crate::expand::storage_entry(entries.len() as u32, true, 0));
    }
    if let Some(format) = pass_output_format(pass) {
        entries.push(wgpu::BindGroupLayoutEntry {
            binding: entries.len() as u32,
            visibility: stage,
            ty: wgpu::BindingType::StorageTexture {
                access: wgpu::StorageTextureAccess::WriteOnly,
                format,
                view_dimension: wgpu::TextureViewDimension::D2,
            },
            count: None,
        });
    }
    if pass == AoPass::Upsample {
        entries.push(crate::expand::storage_entry(entries.len() as u32, false, 0));
    }
    entries
}

/// Workgroup edge of the compute passes (the WGSL's `@workgroup_size(8, 8)`).
const PASS_WORKGROUP: u32 = 8;

/// The storage texture a compute pass writes, after its inputs.
fn pass_output_format(pass: AoPass) -> Option<wgpu::TextureFormat> {
    match pass {
        AoPass::Trace | AoPass::Upsample | AoPass::Retrace => Some(VISIBILITY_FORMAT),
        AoPass::Temporal => Some(HISTORY_FORMAT),
        AoPass::Composite => None,
    }
}

impl AoPasses {
    /// Builds the four pipelines; `frame_layout` is group 0 (frame.wgsl),
    /// `output_format` the frame's target (the composite's output).
    pub fn new(
        device: &wgpu::Device,
        frame_layout: &wgpu::BindGroupLayout,
        output_format: wgpu::TextureFormat,
    ) -> Self {
        let pipelines = AoPass::ALL
            .into_iter()
            .map(|pass| {
                let stage = if pass.is_compute() {
                    wgpu::ShaderStages::COMPUTE
                } else {
                    wgpu::ShaderStages::FRAGMENT
                };
                let entries = pass_layout_entries(pass, stage);
                let textures = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                    label: Some(pass.entry_point()),
                    entries: &entries,
                });
                let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                    label: Some(pass.entry_point()),
                    bind_group_layouts: &[Some(frame_layout), Some(&textures)],
                    immediate_size: 0,
                });
                let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some(pass.entry_point()),
                    source: wgpu::ShaderSource::Wgsl(pass.module_source().into()),
                });
                if pass.is_compute() {
                    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                        label: Some(pass.entry_point()),
                        layout: Some(&layout),
                        module: &module,
                        entry_point: Some(pass.entry_point()),
                        compilation_options: Default::default(),
                        cache: None,
                    });
                    return (pass, PassPipeline::Compute(pipeline), textures);
                }
                let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                    label: Some(pass.entry_point()),
                    layout: Some(&layout),
                    vertex: wgpu::VertexState {
                        module: &module,
                        entry_point: Some("vs_fullscreen"),
                        compilation_options: Default::default(),
                        buffers: &[],
                    },
                    primitive: wgpu::PrimitiveState::default(),
                    depth_stencil: None,
                    multisample: Default::default(),
                    fragment: Some(wgpu::FragmentState {
                        module: &module,
                        entry_point: Some(pass.entry_point()),
                        compilation_options: Default::default(),
                        targets: &[Some(output_format.into())],
                    }),
                    multiview_mask: None,
                    cache: None,
                });
                (pass, PassPipeline::Render(pipeline), textures)
            })
            .collect();
        Self {
            pipelines,
            targets: None,
            current: 0,
            frame_index: 0,
            still_frames: 0,
            history_valid: false,
            prev_view_proj: Mat4::IDENTITY,
            last_settings: None,
            last_visibility: None,
            accumulating: false,
        }
    }

    /// Forgets the history: the next frame starts a new accumulation at jitter index 0.
    pub fn reset_history(&mut self) {
        self.history_valid = false;
        self.frame_index = 0;
    }

    /// The targets, (re)made for `size` and `downscale` (a change resets the history).
    pub fn targets(&mut self, device: &wgpu::Device, size: (u32, u32), downscale: u32) -> &FrameTargets {
        if self.targets.as_ref().is_none_or(|t| t.size != size || t.downscale != downscale) {
            self.targets = Some(FrameTargets::new(device, size, downscale));
            self.reset_history();
        }
        self.targets.as_ref().expect("just made")
    }

    /// The uniform values of the coming frame, given its settings (`None`: AO off).
    pub fn begin_frame(&mut self, settings: Option<&AoSettings>) -> AoFrameState {
        if settings != self.last_settings.as_ref() {
            self.reset_history();
        }
        self.last_settings = settings.copied();
        let Some(s) = settings else {
            self.reset_history();
            return AoFrameState {
                prev_view_proj: self.prev_view_proj,
                sparse: [1.0, 0.0, 0.0, 1.0],
                temporal: [1.0, 0.0, 1.0, 0.0],
                index: 0,
            };
        };
        let f = s.downscale();
        let [ox, oy] = traced_pixel_offset(f, self.frame_index, s.jitter);
        AoFrameState {
            prev_view_proj: self.prev_view_proj,
            sparse: [
                f as f32,
                ox as f32,
                oy as f32,
                match s.upsample {
                    Upsample::Bilinear => 0.0,
                    Upsample::BilateralOnly => 1.0,
                    Upsample::Bilateral => 2.0,
                },
            ],
            temporal: [
                s.accumulated_frames() as f32,
                if self.history_valid { 1.0 } else { 0.0 },
                if s.keep_disoccluded_history { 0.0 } else { 1.0 },
                if s.interleave { 1.0 } else { 0.0 },
            ],
            index: self.frame_index,
        }
    }

    /// The G-buffer attachments of the coming frame: position, normal, colour.
    pub fn gbuffer_views(&self) -> [wgpu::TextureView; 3] {
        let v = &self.targets.as_ref().expect("targets() first").views;
        [v.position[self.current].clone(), v.normal[self.current].clone(), v.colour.clone()]
    }

    fn pass(&self, pass: AoPass) -> (&PassPipeline, &wgpu::BindGroupLayout) {
        let (_, pipeline, layout) = self.pipelines.iter().find(|(p, _, _)| *p == pass).expect("every pass");
        (pipeline, layout)
    }

    /// Records one pass: a compute pass writes its own output (in its bind
    /// group), the composite draws into `target`.
    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        key: InputsKey,
        frame_group: &wgpu::BindGroup,
        targets: &FrameTargets,
        target: &wgpu::TextureView,
        timer: Option<&crate::pass_timer::PassTimer>,
    ) {
        let pass = key.0;
        let (pipeline, layout) = self.pass(pass);
        let mut groups = targets.groups.borrow_mut();
        let group = groups.entry(key).or_insert_with(|| {
            let entries: Vec<wgpu::BindGroupEntry> = targets
                .inputs(key)
                .into_iter()
                .enumerate()
                .map(|(i, resource)| wgpu::BindGroupEntry { binding: i as u32, resource })
                .collect();
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(pass.entry_point()),
                layout,
                entries: &entries,
            })
        });
        match pipeline {
            PassPipeline::Compute(pipeline) => {
                let (width, height) = match pass {
                    AoPass::Trace => (targets.traced.width(), targets.traced.height()),
                    _ => targets.size,
                };
                let mut cpass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some(pass.entry_point()),
                    timestamp_writes: timer.and_then(|t| t.compute_writes(pass.entry_point())),
                });
                cpass.set_pipeline(pipeline);
                cpass.set_bind_group(0, frame_group, &[]);
                cpass.set_bind_group(1, &*group, &[]);
                if pass == AoPass::Retrace {
                    cpass.dispatch_workgroups_indirect(&targets.retrace_queue, RETRACE_DISPATCH_OFFSET);
                } else {
                    cpass.dispatch_workgroups(
                        width.div_ceil(PASS_WORKGROUP),
                        height.div_ceil(PASS_WORKGROUP),
                        1,
                    );
                }
            }
            PassPipeline::Render(pipeline) => {
                let mut rpass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                    label: Some(pass.entry_point()),
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: target,
                        depth_slice: None,
                        resolve_target: None,
                        // Every pixel is written; the clear only matters to a reader of an unwritten target.
                        ops: wgpu::Operations {
                            load: wgpu::LoadOp::Clear(crate::render::background_color()),
                            store: wgpu::StoreOp::Store,
                        },
                    })],
                    depth_stencil_attachment: None,
                    timestamp_writes: timer.and_then(|t| t.render_writes(pass.entry_point())),
                    occlusion_query_set: None,
                    multiview_mask: None,
                });
                rpass.set_pipeline(pipeline);
                rpass.set_bind_group(0, frame_group, &[]);
                rpass.set_bind_group(1, &*group, &[]);
                rpass.draw(0..3, 0..1);
            }
        }
    }

    /// Records the passes after the voxel draw: the AO passes `settings` ask
    /// for (none when `None`: AO off), then the composite into `target`.
    #[allow(clippy::too_many_arguments)]
    pub fn encode(
        &mut self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        frame_group: &wgpu::BindGroup,
        settings: Option<&AoSettings>,
        target: &wgpu::TextureView,
        view_proj: Mat4,
        timer: Option<&crate::pass_timer::PassTimer>,
    ) {
        let t = self.targets.as_ref().expect("targets() first");
        let cur = self.current;
        let mut visibility = None;
        let mut accumulated = false;
        if let Some(s) = settings {
            self.run(device, encoder, (AoPass::Trace, cur, None), frame_group, t, target, timer);
            let mut current = VisibilityTexture::Traced;
            if s.downscale() > 1 {
                let retrace = s.upsample == Upsample::Bilateral;
                if retrace {
                    // An empty queue: count and workgroups 0.
                    encoder.clear_buffer(&t.retrace_queue, 0, Some(RETRACE_DISPATCH_OFFSET + 4));
                }
                self.run(device, encoder, (AoPass::Upsample, cur, None), frame_group, t, target, timer);
                if retrace {
                    self.run(device, encoder, (AoPass::Retrace, cur, None), frame_group, t, target, timer);
                }
                current = VisibilityTexture::Upsampled;
            }
            if s.accumulated_frames() > 1 {
                let key = (AoPass::Temporal, cur, Some(current));
                self.run(device, encoder, key, frame_group, t, target, timer);
                current = VisibilityTexture::History(cur);
                accumulated = true;
            }
            visibility = Some(current);
        }
        self.run(device, encoder, (AoPass::Composite, cur, visibility), frame_group, t, target, timer);
        self.last_visibility = visibility;
        self.history_valid = accumulated;
        self.still_frames =
            if accumulated && view_proj == self.prev_view_proj { self.still_frames + 1 } else { 0 };
        // Every pixel of a still view has N frames in once N frames were drawn
        // since the view last changed (or the history was reset).
        let since = self.still_frames.min(self.frame_index);
        self.accumulating = accumulated && settings.is_some_and(|s| since + 1 < s.accumulated_frames());
        self.frame_index = self.frame_index.wrapping_add(1);
        self.prev_view_proj = view_proj;
        self.current = 1 - cur;
    }

    /// The textures the last frame wrote (`None` before the first frame).
    pub fn last_frame(&self) -> Option<LastFrame<'_>> {
        let t = self.targets.as_ref()?;
        let last = 1 - self.current;
        let visibility = self.last_visibility.map(|v| match v {
            VisibilityTexture::Traced => (&t.traced, 4),
            VisibilityTexture::Upsampled => (&t.upsampled, 4),
            VisibilityTexture::History(i) => (&t.history[i], 16),
        });
        Some(LastFrame { position: &t.position[last], normal: &t.normal[last], visibility })
    }

    /// Whether fewer than N frames were drawn since the view last changed (or
    /// the history was reset): the viewer keeps drawing a still view until
    /// every pixel's AO has its N frames.
    pub fn accumulating(&self) -> bool {
        self.accumulating
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_retrace_shaders_agree_on_the_workgroup_and_the_queue() {
        let retrace = crate::shaders::AO_RETRACE_WGSL;
        let upsample = crate::shaders::AO_UPSAMPLE_WGSL;
        assert!(retrace.contains(&format!("@workgroup_size({RETRACE_WORKGROUP})")));
        assert!(upsample.contains(&format!("slot % {RETRACE_WORKGROUP}u == 0u")));
        // The header: count, then the dispatch's x, y, z, as both structs lay it out.
        for wgsl in [retrace, upsample] {
            let header: Vec<&str> = wgsl
                .lines()
                .map(str::trim)
                .skip_while(|l| !l.starts_with("struct Retrace"))
                .skip(1)
                .filter(|l| !l.starts_with("//"))
                .take(4)
                .map(|l| l.split(':').next().unwrap_or(""))
                .collect();
            assert_eq!(header, ["count", "groups", "groups_y", "groups_z"], "{wgsl}");
        }
        assert_eq!(RETRACE_HEADER, 16);
        assert_eq!(RETRACE_DISPATCH_OFFSET, 4);
        // Room for one pixel in 8, and never less than one workgroup.
        assert_eq!(retrace_queue_bytes((1920, 1080)), 16 + 4 * 259_200);
        assert_eq!(retrace_queue_bytes((4, 4)), 16 + 4 * 64);
    }
}
