//! Occlusion culling from GPU feedback (seed 003 §4). After a frame's blocks
//! are drawn, the bounding box of each block the traversal wants to refine is
//! drawn as a proxy (depth test on, no depth or colour write) inside an
//! occlusion query. The queries resolve into one buffer, copied to one of two
//! readback buffers and read a frame or two later without waiting. A box with
//! no passing sample hides everything below it, so the traversal stops there:
//! a parent is a conservative proxy for its children.
//!
//! Why queries and not a hierarchical-Z pyramid: both work on WebGPU and on
//! lavapipe, but Hi-Z needs a mip chain built by a compute pass over the full
//! depth buffer every frame, which on a CPU adapter (SwiftShader, lavapipe)
//! costs as much as the draw; the queries cost a box per tested block
//! (rasterised against the depth the frame already has) and 8 bytes of readback each.

use std::collections::HashSet;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3};
use voxstream_format::BlockKey;

use crate::render::DEPTH_FORMAT;
use crate::select::Aabb;
use crate::shaders;

/// Blocks tested per frame at most; the coarsest are tested first.
pub const MAX_QUERIES: u32 = 4096;
const BOX_BYTES: u64 = 32;

const IDLE: u8 = 0;
const MAPPING: u8 = 1;
const MAPPED: u8 = 2;
const FAILED: u8 = 3;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct ProxyBox {
    min: [f32; 4],
    max: [f32; 4],
}

struct Readback {
    buffer: wgpu::Buffer,
    state: Arc<AtomicU8>,
    keys: Vec<BlockKey>,
    frame: u64,
}

/// What the GPU saw of the tested blocks in one frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Visibility {
    pub frame: u64,
    pub hidden: HashSet<BlockKey>,
    pub tested: usize,
}

pub struct Occlusion {
    pipeline: wgpu::RenderPipeline,
    group: wgpu::BindGroup,
    uniform: wgpu::Buffer,
    boxes: wgpu::Buffer,
    pub query_set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    readbacks: [Readback; 2],
    /// The readback slot this frame's queries go to, and how many there are.
    current: Option<(usize, u32)>,
}

/// GPU bytes the occlusion machinery holds (counted against the budget).
pub fn occlusion_gpu_bytes() -> u64 {
    MAX_QUERIES as u64 * (BOX_BYTES + 8 + 8 + 8) + 64
}

impl Occlusion {
    pub fn new(device: &wgpu::Device, color_format: wgpu::TextureFormat) -> Self {
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("occlusion proxies"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::VERTEX,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: wgpu::BufferSize::new(64),
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::VERTEX,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: true },
                        has_dynamic_offset: false,
                        min_binding_size: wgpu::BufferSize::new(BOX_BYTES),
                    },
                    count: None,
                },
            ],
        });
        let uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("proxy view"),
            size: 64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let boxes = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("proxy boxes"),
            size: MAX_QUERIES as u64 * BOX_BYTES,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("occlusion proxies"),
            layout: &layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: uniform.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: boxes.as_entire_binding() },
            ],
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("proxy.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::PROXY_WGSL.into()),
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("occlusion proxies"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("occlusion proxies"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs_proxy"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(false),
                depth_compare: Some(wgpu::CompareFunction::LessEqual),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            // The pass has a colour target, so the pipeline names it, writing nothing.
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs_proxy"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: color_format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::empty(),
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let query_set = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("occlusion"),
            ty: wgpu::QueryType::Occlusion,
            count: MAX_QUERIES,
        });
        let resolve = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("occlusion resolve"),
            size: MAX_QUERIES as u64 * 8,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let readback = || Readback {
            buffer: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("occlusion readback"),
                size: MAX_QUERIES as u64 * 8,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            state: Arc::new(AtomicU8::new(IDLE)),
            keys: Vec::new(),
            frame: 0,
        };
        Self {
            pipeline,
            group,
            uniform,
            boxes,
            query_set,
            resolve,
            readbacks: [readback(), readback()],
            current: None,
        }
    }

    /// Prepares this frame's queries for `tests` (block, bounds in the frame's
    /// coordinates), at most [`MAX_QUERIES`]. Nothing is tested while both
    /// readbacks are still in use (the GPU or the map is behind).
    pub fn prepare(&mut self, queue: &wgpu::Queue, view_proj: Mat4, tests: &[(BlockKey, Aabb)], frame: u64) {
        self.current = None;
        let Some(slot) = self.readbacks.iter().position(|r| r.state.load(Ordering::Acquire) == IDLE) else {
            return;
        };
        let n = tests.len().min(MAX_QUERIES as usize);
        if n == 0 {
            return;
        }
        let boxes: Vec<ProxyBox> = tests[..n]
            .iter()
            .map(|(_, b)| ProxyBox { min: b.min.extend(0.0).to_array(), max: b.max.extend(0.0).to_array() })
            .collect();
        queue.write_buffer(&self.boxes, 0, bytemuck::cast_slice(&boxes));
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&view_proj.to_cols_array()));
        let r = &mut self.readbacks[slot];
        r.keys = tests[..n].iter().map(|(k, _)| *k).collect();
        r.frame = frame;
        self.current = Some((slot, n as u32));
    }

    /// The query set the frame's render pass must carry, if anything is tested.
    pub fn query_set(&self) -> Option<&wgpu::QuerySet> {
        self.current.map(|_| &self.query_set)
    }

    /// Draws the proxies, one query each, after the frame's blocks.
    pub fn draw_proxies(&self, pass: &mut wgpu::RenderPass<'_>) {
        let Some((_, n)) = self.current else { return };
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.group, &[]);
        for i in 0..n {
            pass.begin_occlusion_query(i);
            pass.draw(0..36, i..i + 1);
            pass.end_occlusion_query();
        }
    }

    /// Resolves the queries into the readback buffer (after the render pass).
    pub fn resolve(&self, encoder: &mut wgpu::CommandEncoder) {
        let Some((slot, n)) = self.current else { return };
        encoder.resolve_query_set(&self.query_set, 0..n, &self.resolve, 0);
        encoder.copy_buffer_to_buffer(&self.resolve, 0, &self.readbacks[slot].buffer, 0, n as u64 * 8);
    }

    /// Starts mapping this frame's readback (after the submit).
    pub fn after_submit(&mut self) {
        let Some((slot, n)) = self.current.take() else { return };
        let r = &self.readbacks[slot];
        r.state.store(MAPPING, Ordering::Release);
        let state = r.state.clone();
        r.buffer.map_async(wgpu::MapMode::Read, ..n as u64 * 8, move |result| {
            state.store(if result.is_ok() { MAPPED } else { FAILED }, Ordering::Release);
        });
    }

    /// The newest finished readback, if any finished since the last call.
    pub fn take_results(&mut self) -> Option<Visibility> {
        let mut newest: Option<Visibility> = None;
        for r in &mut self.readbacks {
            match r.state.load(Ordering::Acquire) {
                MAPPED => {
                    let n = r.keys.len() as u64;
                    let hidden = match r.buffer.get_mapped_range(..n * 8) {
                        Ok(view) => {
                            let samples: &[u64] = bytemuck::cast_slice(&view);
                            r.keys.iter().zip(samples).filter(|(_, s)| **s == 0).map(|(k, _)| *k).collect()
                        }
                        Err(_) => HashSet::new(),
                    };
                    r.buffer.unmap();
                    r.state.store(IDLE, Ordering::Release);
                    if newest.as_ref().is_none_or(|v| v.frame < r.frame) {
                        newest = Some(Visibility { frame: r.frame, hidden, tested: r.keys.len() });
                    }
                }
                FAILED => r.state.store(IDLE, Ordering::Release),
                _ => {}
            }
        }
        newest
    }
}

/// A block's proxy box: its tight bounds grown by one of its voxels, so the
/// box's faces lie in front of the block's own faces (the test is conservative).
pub fn proxy_bounds(bounds: &Aabb, key: &BlockKey) -> Aabb {
    let grow = Vec3::splat((1u64 << key.level) as f32);
    Aabb { min: bounds.min - grow, max: bounds.max + grow }
}

/// Whether the eye is inside (or on) `bounds`: such a block is always visible,
/// its box would be clipped by the near plane.
pub fn contains_eye(bounds: &Aabb, eye: Vec3) -> bool {
    bounds.distance_to(eye) <= 0.0
}
