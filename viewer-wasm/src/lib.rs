//! voxstream viewer: streams sparse voxel blocks and renders them with wgpu,
//! as WebGPU in the browser (module `web`) and on Vulkan natively for tests
//! ([`offscreen`]). Both targets share every stage of the data flow:
//!
//! [`fetch`] (bytes from HTTP or a store directory) → [`decode`] (validated
//! [`voxstream_format::Block`]) → [`expand`] (compute pass: voxels to face
//! records and indirect draw args) → [`render`] (vertex pulling, shading) with
//! [`ao`] (occupancy volume for cone-traced ambient occlusion). [`camera`] is
//! the orbit camera, [`select`] the screen-space LOD rule and [`scene`] the
//! state that ties them together (block cache, what to fetch, what to draw,
//! stats).

pub mod ao;
pub mod camera;
pub mod decode;
pub mod expand;
pub mod fetch;
pub mod render;
pub mod scene;
pub mod select;
pub mod shaders;
pub mod stats;

#[cfg(not(target_arch = "wasm32"))]
pub mod offscreen;
#[cfg(target_arch = "wasm32")]
mod web;

/// Clear colour of every frame, exactly as it lands in an Rgba8Unorm target.
/// Shaded voxels never take this value (see shaders/voxel.wgsl).
pub const BACKGROUND_RGBA8: [u8; 4] = [20, 24, 36, 255];

/// The format of both the browser canvas and the native offscreen target: no
/// sRGB conversion, so shader outputs land in the image unchanged.
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

pub use camera::OrbitCamera;
pub use scene::Scene;
pub use stats::Stats;
