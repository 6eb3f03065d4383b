// The per-frame uniform and the AO's occupancy structures (group 0), shared by every
// pass of a frame: the voxel draw (voxel.wgsl) and the AO passes (ao_trace,
// ao_upsample, ao_temporal, ao_composite). The viewer prepends this file to
// each of their modules (WGSL has no includes); viewer-wasm/src/render.rs
// (`FrameUniform`) holds the same layout.

struct Frame {
    // Grid units -> clip space, wgpu depth 0..1.
    view_proj: mat4x4<f32>,
    // xyz: camera position in grid units.
    eye: vec4<f32>,
    // xyz: unit direction towards the key light.
    key_light: vec4<f32>,
    // x: grid edge in grid units, y: occupancy cells per edge at mip 0,
    // z: occupancy mip count, w: AO strength (0 disables).
    volume: vec4<f32>,
    // x: cone count, y: tan(half aperture), z: step (fraction of the cone's
    // diameter), w: start offset along the normal (grid units).
    ao_cone: vec4<f32>,
    // x: R (grid units), y: falloff lambda, z: 1 = empty-space skipping,
    // w: 1 = ignore the normal (negative control).
    ao_range: vec4<f32>,
    // Cone axes in the local frame (x, y tangent, z normal), w: weight. This
    // frame's set: rotated about the normal per frame when jitter is on.
    ao_dirs: array<vec4<f32>, 16>,
    // The previous frame's view_proj (temporal reprojection).
    prev_view_proj: mat4x4<f32>,
    // x: trace downscale f (1, 2 or 4: AO is traced for one pixel of each f×f
    // block), yz: that pixel's offset in its block this frame, w: 1 = joint
    // bilateral upsampling, 0 = plain bilinear (comparison only).
    ao_sparse: vec4<f32>,
    // x: N, the frames the history averages (a new frame's weight falls to
    // 1/N; 1 = no accumulation), y: 1 = the history holds the previous frame,
    // z: 1 = reject history where position or normal disagree (disocclusion),
    // w: 1 = interleaved sampling (each traced texel turns the cone set by its
    // own angle).
    ao_temporal: vec4<f32>,
    // x: 1 = the AO field mode: a pixel whose voxel carries the precomputed
    // field (G-buffer position.w = 2 + V) shows that V instead of cones.
    // y: this frame's step phase (0..1), z: 1 = jitter where along each cone
    // its samples fall (ao.wgsl, `first_step_fraction`).
    ao_mode: vec4<f32>,
}

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var occupancy: texture_3d<f32>;
@group(0) @binding(2) var occupancy_sampler: sampler;

// The occupancy clipmap (viewer-wasm/src/clipmap.rs): `levels` cubes of N^3
// cells, level k's cell edge finest * 2^k grid units, its region the cells
// origins[k] .. origins[k] + N, cell w at slot w mod N (toroidal), texel
// slot + (0, 0, k * (N + 1)) of clip_texels: its opacity along x, y and z,
// and their sum, each clamped to 1; texel N of a level's block along an axis
// repeats its slot 0, so a filtered read wraps as the slots do
// (clipmap_texels.wgsl).
struct Clipmap {
    // x: levels, y: cells per edge N, z: finest cell edge (grid units),
    // w: 1 = the AO traces the clipmap, 0 = the volume.
    info: vec4<f32>,
    origins: array<vec4<i32>, 8>,
}

@group(0) @binding(3) var<uniform> clipmap: Clipmap;
@group(0) @binding(4) var clip_texels: texture_3d<f32>;
@group(0) @binding(5) var clip_sampler: sampler;
