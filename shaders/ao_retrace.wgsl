// Pass 2b of the AO (only with the re-tracing upsample, frame.ao_sparse.w =
// 2): the pixels the upsample could not match (ao_upsample.wgsl listed them)
// traced at full resolution into the upsampled V, 64 a workgroup.
// Compacting them into a list instead of tracing each where the upsample
// found it keeps a GPU's SIMD lanes busy: a silhouette crosses many tiles of
// the upsample's dispatch but fills few lanes of each, and a warp pays for a
// trace if one lane traces. Dispatched indirectly: the upsample counted the
// workgroups. Module: frame.wgsl, screen.wgsl, ao.wgsl, this.

// ao_upsample.wgsl's `RetraceQueue`, read as plain words.
struct RetraceList {
    count: u32,
    // The indirect dispatch: workgroups, 1, 1.
    groups: u32,
    groups_y: u32,
    groups_z: u32,
    // x | y << 16 per pixel.
    pixels: array<u32>,
}

@group(1) @binding(0) var gbuffer_position: texture_2d<f32>;
@group(1) @binding(1) var gbuffer_normal: texture_2d<f32>;
@group(1) @binding(2) var<storage, read> retrace: RetraceList;
@group(1) @binding(3) var upsampled_out: texture_storage_2d<r32float, write>;

@compute @workgroup_size(64)
fn cs_retrace(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= min(retrace.count, arrayLength(&retrace.pixels)) {
        return;
    }
    let packed = retrace.pixels[id.x];
    let pixel = vec2<i32>(i32(packed & 0xffffu), i32(packed >> 16u));
    let here = load_surface(gbuffer_position, gbuffer_normal, pixel);
    let v = surface_visibility(here, interleaved_turn(pixel));
    textureStore(upsampled_out, pixel, vec4<f32>(v, 0.0, 0.0, 1.0));
}
