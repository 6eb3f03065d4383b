// Pass 3 of the AO (only when frames are accumulated, N > 1): temporal
// accumulation. The pixel's surface point is reprojected with the previous
// frame's view_proj; the history there (V, frames) is kept when the previous
// frame saw the same surface there (its point within `surface_tolerance` of
// this pixel's tangent plane and within 8 of them in all, normals within about
// 25°), else dropped (disocclusion, a camera jump). The
// blend is exponential with a weight that falls to 1/N:
//
//   frames' = min(frames + 1, N),  V' = V_history + (V - V_history) / frames'
//
// so a still camera averages its first N jittered frames exactly and then
// keeps a moving average of about N frames. Writes (V', frames', 0, 1).

@group(1) @binding(0) var gbuffer_position: texture_2d<f32>;
@group(1) @binding(1) var gbuffer_normal: texture_2d<f32>;
@group(1) @binding(2) var current_ao: texture_2d<f32>;
@group(1) @binding(3) var previous_position: texture_2d<f32>;
@group(1) @binding(4) var previous_normal: texture_2d<f32>;
@group(1) @binding(5) var history: texture_2d<f32>;
@group(1) @binding(6) var history_out: texture_storage_2d<rgba32float, write>;

@compute @workgroup_size(8, 8)
fn cs_temporal(@builtin(global_invocation_id) id: vec3<u32>) {
    let size = textureDimensions(history_out);
    if id.x >= size.x || id.y >= size.y {
        return;
    }
    textureStore(history_out, vec2<i32>(id.xy), temporal_pixel(vec2<i32>(id.xy)));
}

fn temporal_pixel(pixel: vec2<i32>) -> vec4<f32> {
    let size = vec2<f32>(textureDimensions(gbuffer_normal));
    let v = textureLoad(current_ao, pixel, 0).r;
    let here = load_surface(gbuffer_position, gbuffer_normal, pixel);
    if !here.surface {
        return vec4<f32>(1.0, 0.0, 0.0, 1.0);
    }
    let fresh = vec4<f32>(v, 1.0, 0.0, 1.0);
    let max_frames = max(frame.ao_temporal.x, 1.0);
    if max_frames <= 1.0 || frame.ao_temporal.y < 0.5 {
        return fresh;
    }
    let previous_clip = frame.prev_view_proj * vec4<f32>(here.position, 1.0);
    if previous_clip.w <= 0.0 {
        return fresh;
    }
    let ndc = previous_clip.xy / previous_clip.w;
    let at = vec2<f32>(ndc.x * 0.5 + 0.5, 0.5 - ndc.y * 0.5) * size;
    if any(at < vec2<f32>(0.0)) || any(at >= size) {
        return fresh;
    }
    let previous_pixel = vec2<i32>(floor(at));
    let h = textureLoad(history, previous_pixel, 0);
    let before = load_surface(previous_position, previous_normal, previous_pixel);
    var keep = before.surface && h.y >= 1.0;
    if frame.ao_temporal.z > 0.5 {
        // Off the pixel's tangent plane: another surface (disocclusion). Along
        // it the nearest previous pixel may lie a footprint away on a grazing
        // surface, which is the same surface: allowed up to 8 tolerances.
        let tolerance = surface_tolerance(here.position);
        let offset = before.position - here.position;
        keep = keep && abs(dot(offset, here.normal)) <= tolerance && length(offset) <= 8.0 * tolerance
            && dot(before.normal, here.normal) > 0.9;
    }
    if !keep {
        return fresh;
    }
    let frames = min(h.y + 1.0, max_frames);
    return vec4<f32>(h.x + (v - h.x) / frames, frames, 0.0, 1.0);
}
