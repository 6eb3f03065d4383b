// Ambient occlusion by voxel cone tracing (seed 000 §5, seed 001 §4) through
// the occupancy volume (viewer-wasm/src/ao.rs), estimating the definition of
// issue 9:
//
//   V(p, n) = 1 - (1/pi) * integral over the hemisphere of w(d) cos(theta),
//   w(d) = 1 / (1 + lambda * d / R) for d <= R, else 0.
//
// The cone axes are a fixed cosine-weighted set (frame.ao_dirs, equal
// weights), so V = 1 - sum_i weight_i * occlusion_i. Along a cone,
// front-to-back opacity alpha accumulates; a step adds
// (1 - alpha) * alpha_step * w(d), d the distance from p to the sample (grid
// units, the same units as R). Part of the trace pass's module (after
// frame.wgsl, whose `frame`, `occupancy` and `occupancy_sampler` bindings it
// reads; ao_trace.wgsl calls `ambient_visibility`).

// Occlusion (0 = open, 1 = blocked, weighted by w(d)) seen by one cone from p.
//
// - Start: p + n * offset (frame.ao_cone.w, 1.5 finest cells by default): the
//   surface's own voxels fill the cell p lies on, so a cone starting on it
//   would see itself.
// - Width: the cone's diameter 2 * tan(aperture) * d picks the mip (fractional:
//   the sampler's linear mip filter makes it quadrilinear), never finer than
//   one cell, and never wider than the sample's height above p's tangent plane:
//   a trilinear sample reaches about one cell around it, so a wider one would
//   read the surface the cone starts from.
// - Opacity: a cell's value is its opacity to a ray crossing it (ao.rs); a step
//   of length s through cells of edge c has alpha_step = 1 - (1 - o)^(s / c).
// - Empty-space skipping: where the mip two levels coarser reads 0, the whole
//   neighbourhood is empty and the cone jumps half of that mip's cell.
fn trace_cone(p: vec3<f32>, n: vec3<f32>, dir: vec3<f32>, cell: f32, max_mip: f32) -> f32 {
    let grid = frame.volume.x;
    let tan_half = frame.ao_cone.y;
    let step_fraction = frame.ao_cone.z;
    let offset = frame.ao_cone.w;
    let radius = frame.ao_range.x;
    let falloff = frame.ao_range.y;
    let skip = frame.ao_range.z > 0.5;
    let origin = p + n * offset;
    var alpha = 0.0;
    var occlusion = 0.0;
    var t = 0.0;
    for (var step = 0u; step < 128u; step += 1u) {
        let s = origin + dir * t;
        let d = length(s - p);
        if d > radius || alpha > 0.995 {
            break;
        }
        let uvw = s / grid;
        if any(uvw < vec3<f32>(0.0)) || any(uvw > vec3<f32>(1.0)) {
            break;
        }
        let height = max(dot(s - p, n), cell);
        let diameter = clamp(2.0 * tan_half * d, cell, max(height / 3.0, cell));
        let mip = clamp(log2(diameter / cell), 0.0, max_mip);
        let step_len = max(step_fraction * diameter, 0.5 * cell);
        if skip && mip + 2.0 <= max_mip {
            let coarse = textureSampleLevel(occupancy, occupancy_sampler, uvw, mip + 2.0).r;
            if coarse <= 0.0 {
                t += max(step_len, 0.5 * cell * exp2(mip + 2.0));
                continue;
            }
        }
        let o = textureSampleLevel(occupancy, occupancy_sampler, uvw, mip).r;
        if o > 0.0 {
            let edge = cell * exp2(mip);
            let a = 1.0 - pow(max(1.0 - o, 0.0), step_len / edge);
            // The opacity ramps up over the texel edge before a surface, so a
            // step's occlusion sits about half an edge further than its sample.
            let w = 1.0 / (1.0 + falloff * (d + 0.5 * edge) / radius);
            occlusion += (1.0 - alpha) * a * w;
            alpha += (1.0 - alpha) * a;
        }
        t += step_len;
    }
    return occlusion;
}

// V(p, n) in [0, 1] at grid position `p` with unit normal `n`, the cone set
// (frame.ao_dirs) turned about n by `turn` (a fraction of a full turn).
fn ambient_visibility(p: vec3<f32>, n_in: vec3<f32>, turn: f32) -> f32 {
    if frame.volume.w <= 0.0 {
        return 1.0;
    }
    var n = n_in;
    if frame.ao_range.w > 0.5 {
        // Negative control only: cones laid around +Z whatever the surface.
        n = vec3<f32>(0.0, 0.0, 1.0);
    }
    let grid = frame.volume.x;
    let cell = grid / frame.volume.y;
    let max_mip = frame.volume.z - 1.0;
    let helper = select(vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(1.0, 0.0, 0.0), abs(n.y) > 0.9);
    let t0 = normalize(cross(helper, n));
    let b0 = cross(n, t0);
    let angle = 6.283185307 * turn;
    let t = cos(angle) * t0 + sin(angle) * b0;
    let b = cross(n, t);
    let cones = u32(frame.ao_cone.x);
    var occluded = 0.0;
    for (var i = 0u; i < cones; i += 1u) {
        let a = frame.ao_dirs[i];
        let dir = normalize(t * a.x + b * a.y + n * a.z);
        occluded += a.w * trace_cone(p, n, dir, cell, max_mip);
    }
    return clamp(1.0 - occluded, 0.0, 1.0);
}
