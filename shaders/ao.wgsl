// Ambient occlusion by voxel cone tracing (seed 000 §5, seed 001 §4), crude
// version: cones march through an occupancy volume splatted from the loaded
// blocks, reading the mip whose cell matches the cone diameter and compositing
// occlusion front to back. Appended to voxel.wgsl, whose `frame`, `occupancy`
// and `occupancy_sampler` bindings it reads.

const CONE_COUNT: u32 = 6u;
// tan(half aperture): 0.55 ~ 57 degree cones, wide enough to overlap (seed 000 §5.6).
const CONE_TAN: f32 = 0.55;
const MAX_STEPS: u32 = 10u;
// Falloff 1 / (1 + lambda * r) with r in occupancy cells.
const FALLOFF: f32 = 0.04;

// Cone axes in the local frame (tangent, bitangent, normal): one along the
// normal and five on a ring 50 degrees away from it.
fn cone_axis(i: u32) -> vec3<f32> {
    if i == 0u {
        return vec3<f32>(0.0, 0.0, 1.0);
    }
    let phi = f32(i - 1u) * (6.2831853 / 5.0);
    let s = 0.7660444; // sin 50
    let c = 0.6427876; // cos 50
    return vec3<f32>(s * cos(phi), s * sin(phi), c);
}

fn cone_weight(i: u32) -> f32 {
    // Cosine-weighted: the normal cone counts more than the tilted ones.
    if i == 0u {
        return 1.0;
    }
    return 0.6427876;
}

// Occlusion (0 = open, 1 = blocked) seen by one cone from `origin`.
fn trace_cone(origin: vec3<f32>, dir: vec3<f32>, cell: f32, max_mip: f32, max_dist: f32) -> f32 {
    let grid = frame.volume.x;
    var occlusion = 0.0;
    var dist = cell;
    for (var step = 0u; step < MAX_STEPS; step += 1u) {
        if dist > max_dist || occlusion > 0.97 {
            break;
        }
        let diameter = max(2.0 * CONE_TAN * dist, cell);
        let mip = clamp(log2(diameter / cell), 0.0, max_mip);
        let p = (origin + dir * dist) / grid;
        if any(p < vec3<f32>(0.0)) || any(p > vec3<f32>(1.0)) {
            break;
        }
        let density = textureSampleLevel(occupancy, occupancy_sampler, p, mip).r;
        let weighted = density / (1.0 + FALLOFF * dist / cell);
        occlusion += (1.0 - occlusion) * weighted;
        dist += max(diameter * 0.5, cell);
    }
    return occlusion;
}

// Fraction (0..1) of the hemisphere around `n` that is open at grid position `p`.
fn ambient_visibility(p: vec3<f32>, n: vec3<f32>) -> f32 {
    let strength = frame.volume.w;
    if strength <= 0.0 {
        return 1.0;
    }
    let grid = frame.volume.x;
    let cell = grid / frame.volume.y;
    let max_mip = frame.volume.z - 1.0;
    let helper = select(vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(1.0, 0.0, 0.0), abs(n.y) > 0.9);
    let t = normalize(cross(helper, n));
    let b = cross(n, t);
    // Start 1.5 finest-cell diagonals off the surface to escape the surface's
    // own occupancy (seed 000 §5.2).
    let origin = p + n * (1.5 * cell);
    let max_dist = 0.3 * grid;
    var occluded = 0.0;
    var total = 0.0;
    for (var i = 0u; i < CONE_COUNT; i += 1u) {
        let a = cone_axis(i);
        let dir = normalize(t * a.x + b * a.y + n * a.z);
        let w = cone_weight(i);
        occluded += w * trace_cone(origin, dir, cell, max_mip, max_dist);
        total += w;
    }
    return clamp(1.0 - strength * occluded / total, 0.0, 1.0);
}
