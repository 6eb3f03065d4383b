//! voxstream viewer: streams sparse voxel blocks and renders them with wgpu,
//! as WebGPU in the browser (module `web`) and on Vulkan natively for tests
//! ([`offscreen`]). Both targets share every stage of the data flow:
//!
//! [`traverse`] (what the view wants: frustum, 1 px error, occlusion
//! feedback, byte budget) → [`request`] (the fetch queue; [`fetch`] gets bytes
//! from HTTP or a store directory) → [`decode`] (validated
//! [`voxstream_format::Block`]) → upload and [`expand`] (one staging write per
//! frame, compute pass: voxels to face records and indirect draw args) →
//! [`render`] (vertex pulling, shading, with [`ao`]) → feedback.
//! [`residency`] holds GPU memory under a hard budget, blocks' faces in the
//! [`face_arena`], [`camera`] is the
//! camera, [`select`] the LOD geometry and [`scene`] the thin driver.

pub mod ao;
pub mod ao_passes;
pub mod camera;
pub mod clipmap;
pub mod crossfade;
pub mod decode;
pub mod expand;
pub mod face_arena;
pub mod fetch;
pub mod occlusion;
pub mod pass_timer;
pub mod render;
pub mod request;
pub mod residency;
pub mod scene;
pub mod select;
pub mod shaders;
pub mod stats;
pub mod traverse;

#[cfg(not(target_arch = "wasm32"))]
pub mod offscreen;
#[cfg(target_arch = "wasm32")]
mod web;
#[cfg(target_arch = "wasm32")]
pub mod worker;

/// Clear colour of every frame, exactly as it lands in an Rgba8Unorm target.
/// Shaded voxels never take this value (see shaders/voxel.wgsl).
pub const BACKGROUND_RGBA8: [u8; 4] = [20, 24, 36, 255];

/// The format of both the browser canvas and the native offscreen target: no
/// sRGB conversion, so shader outputs land in the image unchanged.
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

pub use camera::OrbitCamera;
pub use scene::Scene;
pub use stats::Stats;
