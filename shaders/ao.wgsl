// Ambient occlusion by voxel cone tracing (seed 000 §5, seed 001 §4) through
// the occupancy clipmap (viewer-wasm/src/clipmap.rs) or, for comparison, the
// single occupancy volume (viewer-wasm/src/ao.rs), estimating the definition
// of issue 9:
//
//   V(p, n) = 1 - (1/pi) * integral over the hemisphere of w(d) cos(theta),
//   w(d) = 1 / (1 + lambda * d / R) for d <= R, else 0.
//
// The cone axes are a fixed cosine-weighted set (frame.ao_dirs, equal
// weights), so V = 1 - sum_i weight_i * occlusion_i. Along a cone,
// front-to-back opacity alpha accumulates; a step adds
// (1 - alpha) * alpha_step * w(d), d the distance from p to the sample (grid
// units, the same units as R). Part of the trace pass's module (after
// frame.wgsl, whose `frame`, `occupancy`, `occupancy_sampler`, `clipmap`,
// `clip_texels` and `clip_sampler` bindings it reads; ao_trace.wgsl calls
// `ambient_visibility`).

// Edge of a level's cell in grid units.
fn clip_cell_edge(level: u32) -> f32 {
    return clipmap.info.z * exp2(f32(level));
}

// The scene grid's extent in a level's cells (at least one).
fn clip_grid_cells(level: u32) -> f32 {
    return max(ceil(frame.volume.x / clip_cell_edge(level)), 1.0);
}

// Whether all eight cells a trilinear sample at `p` (grid units) reads are
// known: each lies in the level or outside the scene grid (empty). A level
// whose face lies on the grid's face thus holds samples up to that face.
fn clip_contains(level: u32, p: vec3<f32>) -> bool {
    let q = p / clip_cell_edge(level) - 0.5;
    let o = vec3<f32>(clipmap.origins[level].xyz);
    let n = clipmap.info.y;
    let lo = select(o, vec3<f32>(-1e30), o <= vec3<f32>(0.0));
    let hi = select(o + n - 1.0, vec3<f32>(1e30), o + n >= vec3<f32>(clip_grid_cells(level)));
    return all(q >= lo) && all(q < hi);
}

// Whether `p` lies `margin` cells inside the level's faces, faces on or
// beyond the grid's boundary excepted (nothing lies past them).
fn clip_holds_within(level: u32, p: vec3<f32>, margin: f32) -> bool {
    let edge = clip_cell_edge(level);
    let q = p / edge - 0.5;
    let o = vec3<f32>(clipmap.origins[level].xyz);
    let n = clipmap.info.y;
    let grid_cells = frame.volume.x / edge;
    let lo = select(o + margin, vec3<f32>(-1e30), o <= vec3<f32>(0.0));
    let hi = select(o + n - 1.0 - margin, vec3<f32>(1e30), o + n >= vec3<f32>(grid_cells));
    return clip_contains(level, p) && all(q >= lo) && all(q < hi);
}

// Cells a surface point must lie inside a level for that level to be its own
// (start offset, narrowest cone): the first samples of every cone, whose
// height above the surface is a few cells at most, then stay in the level.
const CLIP_HOME_MARGIN: f32 = 12.0;

// Trilinear opacity of one level at `p` (grid units) to a cone whose axes
// weigh `w` (cone_axis_weights): one filtered read of the level's texels.
//
// - Cells outside the scene grid are empty: the read moves onto the grid's
//   last cell centre along each axis where its footprint crosses a face, and
//   is scaled by the tent weight the grid's cells had there, which is the
//   trilinear sum with the outside cells at 0 (a slot outside the grid may
//   hold a cell from the level's other side).
// - The opacity is the axes' filtered opacities weighed by w, at most their
//   filtered sum (the fourth channel): what each cell's own
//   min(sum of weighed axes, 1) interpolates to wherever the cells agree on
//   which bound applies, which a filtered read cannot do per cell. (Reading
//   the cells one by one, 8 of them with 3 words each, cost 4-6 times as
//   many loads: docs/ao-benchmark.md, "Filtered texels".)
fn clip_trilinear(level: u32, p: vec3<f32>, w: vec3<f32>) -> f32 {
    let q = p / clip_cell_edge(level) - 0.5;
    let g = clip_grid_cells(level);
    let qc = clamp(q, vec3<f32>(0.0), vec3<f32>(g - 1.0));
    let inside = max(vec3<f32>(1.0) - abs(q - qc), vec3<f32>(0.0));
    // The slot, continuous (texel centres at +0.5), in the level's block.
    let n = clipmap.info.y;
    let slot = qc - n * floor(qc / n) + 0.5 + vec3<f32>(0.0, 0.0, f32(level) * (n + 1.0));
    // The atlas may hold more levels than the layout (OccupancyClipmap::reserve).
    let size = vec3<f32>(textureDimensions(clip_texels));
    let texel = textureSampleLevel(clip_texels, clip_sampler, slot / size, 0.0);
    return min(dot(texel.xyz, w), texel.w) * inside.x * inside.y * inside.z;
}

// Quadrilinear clipmap sample: trilinear in the levels floor(lod) and the next,
// blended by lod's fraction. Where p lies outside the level the cone's width
// asks for (far from the camera), the first coarser level holding p stands in.
// Returns (opacity, the level actually read). (Narrow samples once read the
// one cell they lie in, a box read, so that a cone running beside a surface
// did not read the half cell of opacity the tent spreads past its faces; the
// opacity per axis (cone_axis_weights) removed that error at every level and
// the box reads then added error: docs/ao-benchmark.md, "Opacity per axis".)
fn clip_sample(p: vec3<f32>, lod: f32, w: vec3<f32>) -> vec2<f32> {
    let levels = u32(clipmap.info.x);
    var level = u32(clamp(floor(lod), 0.0, f32(levels - 1u)));
    var frac = clamp(lod - f32(level), 0.0, 1.0);
    loop {
        if level + 1u >= levels || clip_contains(level, p) {
            break;
        }
        level += 1u;
        frac = 0.0;
    }
    if !clip_contains(level, p) {
        return vec2<f32>(0.0, f32(level));
    }
    var v = clip_trilinear(level, p, w);
    if frac > 0.0 && level + 1u < levels && clip_contains(level + 1u, p) {
        v = mix(v, clip_trilinear(level + 1u, p, w), frac);
    } else {
        frac = 0.0;
    }
    return vec2<f32>(v, f32(level) + frac);
}

// Opacity at grid position `s` for a cone of width 2^lod finest cells, from
// the clipmap or the volume (frame.volume.y/z describe whichever is traced):
// (opacity, the lod actually read).
fn occupancy_at(s: vec3<f32>, lod: f32, axis_weight: vec3<f32>) -> vec2<f32> {
    if clipmap.info.w > 0.5 {
        return clip_sample(s, lod, axis_weight);
    }
    return vec2<f32>(textureSampleLevel(occupancy, occupancy_sampler, s / frame.volume.x, lod).r, lod);
}

// How much a cell's opacity along each axis counts for a cone along unit
// `dir`: |dir_a| / max_b |dir_b| (seed 001's anisotropic opacity). A cell
// opaque along a holds a surface facing a, somewhere within it; a ray that
// crosses the cell along its dominant axis crosses that surface's plane with
// probability |dir_a| / max |dir|, and a ray running along the surface never
// does. The dominant axis counts fully, so a surface a cone meets head-on or
// at up to 45 degrees stays opaque to it.
fn cone_axis_weights(dir: vec3<f32>) -> vec3<f32> {
    let a = abs(dir);
    return a / max(max(a.x, a.y), max(a.z, 1e-6));
}

// Occlusion (0 = open, 1 = blocked, weighted by w(d)) seen by one cone from p.
//
// - Start (the start-offset rule): p + n * offset_cells * c, c the cell edge
//   of the finest clipmap level that holds p and its neighbourhood (the
//   volume's cell with the volume), offset_cells = 1.5 by default
//   (frame.ao_cone.w is offset_cells * the finest cell): the surface's own
//   voxels fill the cell p lies in, and a trilinear sample reaches half a
//   cell further, so a cone starting closer would see its own surface. The
//   same c is the narrowest cone width.
// - Width: the cone's diameter D = 2 * tan(aperture) * d, never below one
//   cell and never above a third of the sample's height above p's tangent
//   plane (so it never reads the surface it starts from), picks the clipmap
//   level or volume mip (fractional: quadrilinear) whose cells are D / 2: a
//   trilinear sample's tent reaches one cell around it, so the cells read
//   are those the cone's cross-section covers, not twice as far. (Cells of
//   D spread a surface a whole D before it: a cone that ends at R or leaves
//   the grid just short of a surface counted it, and a cone crossing a thin
//   wall sampled only its tent's flanks: docs/ao-benchmark.md, "Cells of
//   half the cone's width".)
// - Opacity: a cell's value is its opacity to a ray crossing it (ao.rs), per
//   axis in the clipmap, weighed by cone_axis_weights; a step of length s
//   through cells of edge c has alpha_step = 1 - (1 - o)^(s / c).
// - Empty-space skipping: where the level (mip) two coarser reads 0, the whole
//   neighbourhood is empty and the cone jumps half of that level's cell.
// - Phase: the first step is `first_step` (0..1] of a step, so the samples
//   fall at distances jittered per frame and texel (first_step_fraction).
// - Bend (0..1, crevice_bend): how far the path comes back down to the
//   cone's own axis from p once that axis rises above the start offset. At
//   1 a sample t along the cone lies max(offset, t * n.dir) above p's tangent
//   plane instead of offset + t * n.dir: in a crevice the raised start would
//   put every cone half-way up the gap, grazing the surface above.
fn trace_cone(p: vec3<f32>, n: vec3<f32>, dir: vec3<f32>, base_cell: f32, cell: f32, max_mip: f32, first_step: f32, bend: f32) -> f32 {
    let grid = frame.volume.x;
    let tan_half = frame.ao_cone.y;
    let step_fraction = frame.ao_cone.z;
    let offset = frame.ao_cone.w * cell / base_cell;
    let radius = frame.ao_range.x;
    let falloff = frame.ao_range.y;
    let skip = frame.ao_range.z > 0.5;
    let origin = p + n * offset;
    let rise = dot(dir, n);
    let axis_weight = cone_axis_weights(dir);
    var alpha = 0.0;
    var occlusion = 0.0;
    var t = 0.0;
    for (var step = 0u; step < 128u; step += 1u) {
        let s = origin + dir * t - n * (bend * min(rise * t, offset));
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
        // A trilinear sample of cells of edge c reads a tent reaching c from
        // it: cells of half the diameter make that reach the cone's radius.
        let mip = clamp(log2(diameter / base_cell) - 1.0, 0.0, max_mip);
        var step_len = max(step_fraction * diameter, 0.5 * cell);
        if step == 0u {
            // The first sample stands for a part of its step, so the rest fall
            // at a jittered phase (first_step_fraction).
            step_len *= first_step;
        }
        if skip && mip + 2.0 <= max_mip {
            let coarse = occupancy_at(s, mip + 2.0, vec3<f32>(1.0));
            if coarse.x <= 0.0 {
                t += max(step_len, 0.5 * base_cell * exp2(coarse.y));
                continue;
            }
        }
        let sample = occupancy_at(s, mip, axis_weight);
        // A sample outside the clipmap level its width asks for came from a
        // coarser one; where that level's cells are wider than the width
        // clamp allows, it would read the surface the cone starts from.
        if sample.y > mip + 0.5 && base_cell * exp2(floor(sample.y)) > max(height / 3.0, cell) {
            t += step_len;
            continue;
        }
        let o = sample.x;
        if o > 0.0 {
            let edge = base_cell * exp2(sample.y);
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

// The crevice probe (crevice_bend): the first cell above p along the normal
// that is at least this opaque counts as a surface over p.
const CREVICE_OPACITY: f32 = 0.5;
// Heights (in cells of p's level) where the bend is full (at or below
// CREVICE_FULL) and none (at or above CREVICE_NONE); the probe's samples lie
// 1.5 (the start offset) to CREVICE_NONE cells up, one cell apart.
const CREVICE_FULL: f32 = 4.5;
const CREVICE_NONE: f32 = 7.5;

// How much the cones from p bend back to their axes (trace_cone): 1 where a
// surface hangs within CREVICE_FULL cells over p, 0 where none does within
// CREVICE_NONE, linear between. Why only there: on an open, rough scan
// (Cedar Creek) cones that run close along the surface read its voxelized
// bumps, which are rougher than its triangles (bent everywhere: 51 -> 13
// equal-error rays); under an overhang the raised start is what darkens the
// crevice (the sphere on a plane: 20 -> 37 rays with the probe).
// docs/ao-benchmark.md, "The start offset and the sphere's contact crevice".
fn crevice_bend(p: vec3<f32>, n: vec3<f32>, base_cell: f32, cell: f32) -> f32 {
    let lod = log2(cell / base_cell);
    let weight = cone_axis_weights(n);
    var h = 1.5;
    loop {
        if h > CREVICE_NONE {
            return 0.0;
        }
        if occupancy_at(p + n * (h * cell), lod, weight).x > CREVICE_OPACITY {
            break;
        }
        h += 1.0;
    }
    return clamp((CREVICE_NONE - h) / (CREVICE_NONE - CREVICE_FULL), 0.0, 1.0);
}

// The fraction (0..1] of a step that the cones' first step takes: 1 without
// jitter; with it, the frame's phase (frame.ao_mode.y; 0 in frame 0, whose
// cones are then the fixed set's) moved by the texel's interleaved `turn`, so
// that the temporal pass averages samples placed all along each cone instead
// of at the same points of the cells every frame.
fn first_step_fraction(turn: f32) -> f32 {
    if frame.ao_mode.z < 0.5 {
        return 1.0;
    }
    return 1.0 - fract(frame.ao_mode.y + 0.7548777 * turn);
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
    let base_cell = grid / frame.volume.y;
    let max_mip = frame.volume.z - 1.0;
    // The cell at p: the finest clipmap level holding p (its neighbourhood
    // within the start offset and the first samples) sets the start offset
    // and the narrowest cone width, so a point outside the finest level does
    // not read its own surface smeared over a coarser level's cells.
    var cell = base_cell;
    if clipmap.info.w > 0.5 {
        let levels = u32(clipmap.info.x);
        var level = 0u;
        loop {
            if level + 1u >= levels || clip_holds_within(level, p, CLIP_HOME_MARGIN) {
                break;
            }
            level += 1u;
        }
        cell = clip_cell_edge(level);
    }
    let helper = select(vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(1.0, 0.0, 0.0), abs(n.y) > 0.9);
    let t0 = normalize(cross(helper, n));
    let b0 = cross(n, t0);
    let angle = 6.283185307 * turn;
    let t = cos(angle) * t0 + sin(angle) * b0;
    let b = cross(n, t);
    let cones = u32(frame.ao_cone.x);
    let first_step = first_step_fraction(turn);
    let bend = crevice_bend(p, n, base_cell, cell);
    var occluded = 0.0;
    for (var i = 0u; i < cones; i += 1u) {
        let a = frame.ao_dirs[i];
        let dir = normalize(t * a.x + b * a.y + n * a.z);
        occluded += a.w * trace_cone(p, n, dir, base_cell, cell, max_mip, first_step, bend);
    }
    return clamp(1.0 - occluded, 0.0, 1.0);
}

// The turn (a fraction of a full turn) of the cone set at image cell `cell`:
// with interleaved sampling on, interleaved gradient noise, so neighbouring
// cells (which the upsample and the eye average) see different cone sets.
fn interleaved_turn(cell: vec2<i32>) -> f32 {
    if frame.ao_temporal.w < 0.5 {
        return 0.0;
    }
    return fract(52.9829189 * fract(dot(vec2<f32>(cell), vec2<f32>(0.06711056, 0.00583715))));
}

// V at a G-buffer surface (screen.wgsl's `Surface`): the voxel's precomputed
// AO field in the field mode where it has one, else the cones turned by `turn`.
fn surface_visibility(s: Surface, turn: f32) -> f32 {
    if frame.ao_mode.x > 0.5 && s.field >= 0.0 && frame.volume.w > 0.0 {
        return s.field;
    }
    return ambient_visibility(s.position, s.normal, turn);
}
