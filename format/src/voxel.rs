use bytemuck::{Pod, Zeroable};

use crate::{BLOCK_SIZE, BlockKey};

/// One of the six axis-aligned faces of a voxel. Bit `i` of a face mask is
/// face `i`: axis `i / 2` (x, y, z), pointing negative when `i` is even.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Face {
    NegX = 0,
    PosX = 1,
    NegY = 2,
    PosY = 3,
    NegZ = 4,
    PosZ = 5,
}

impl Face {
    pub const ALL: [Face; 6] = [Face::NegX, Face::PosX, Face::NegY, Face::PosY, Face::NegZ, Face::PosZ];

    pub fn bit(self) -> u8 {
        1 << self as u8
    }

    pub fn axis(self) -> usize {
        self as usize / 2
    }

    /// +1 or -1 along [`Face::axis`].
    pub fn sign(self) -> i32 {
        if self as u8 & 1 == 1 { 1 } else { -1 }
    }

    /// The four corners of this face of the cube at `min` with edge `size`,
    /// counter-clockwise seen from outside the cube (the GPU's front faces; see
    /// shaders/voxel.wgsl).
    pub fn corners(self, min: [f64; 3], size: f64) -> [[f64; 3]; 4] {
        let axis = self.axis();
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        let positive = self.sign() > 0;
        let uv: [(f64, f64); 4] = if positive {
            [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]
        } else {
            [(0.0, 0.0), (0.0, 1.0), (1.0, 1.0), (1.0, 0.0)]
        };
        uv.map(|(a, b)| {
            let mut p = min;
            p[axis] += if positive { size } else { 0.0 };
            p[u] += a * size;
            p[v] += b * size;
            p
        })
    }
}

/// A voxel as decoded from a block and as read by the GPU: 12 bytes.
///
/// - `pos_faces` = `x | y << 6 | z << 12 | faces << 18 | coverage << 24`
///   (x, y, z < 64, block-local; coverage 1..=255 is the fraction of the
///   level-0 voxels under this voxel that are occupied, 255 = all, see
///   [`coverage_from_count`]; always 255 on level 0);
/// - `normal` = octahedral unit normal, two snorm8 halves (x low); bits 16..24
///   the precomputed AO field's visibility for this voxel (`1 + round(254·V)`,
///   0 = the block has no field, see [`PackedVoxel::field`]), bits 24..32 zero;
/// - `color` = sRGB8 `r | g << 8 | b << 16 | 255 << 24` when the block has
///   colour, 0 when it has none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable, Default)]
#[repr(C)]
pub struct PackedVoxel {
    pub pos_faces: u32,
    pub normal: u32,
    pub color: u32,
}

/// Coverage of a full voxel.
pub const FULL_COVERAGE: u8 = 255;

impl PackedVoxel {
    /// A full-coverage, uncoloured voxel.
    pub fn new(local: [u32; 3], faces: u8, normal: u32) -> Self {
        debug_assert!(local.iter().all(|&c| c < BLOCK_SIZE) && faces < 64);
        Self {
            pos_faces: local[0]
                | local[1] << 6
                | local[2] << 12
                | (faces as u32) << 18
                | (FULL_COVERAGE as u32) << 24,
            normal,
            color: 0,
        }
    }

    pub fn with_coverage(mut self, coverage: u8) -> Self {
        self.pos_faces = (self.pos_faces & 0x00ff_ffff) | (coverage as u32) << 24;
        self
    }

    pub fn with_color(mut self, rgb: [u8; 3]) -> Self {
        self.color = u32::from_le_bytes([rgb[0], rgb[1], rgb[2], 255]);
        self
    }

    pub fn local(&self) -> [u32; 3] {
        [self.pos_faces & 63, (self.pos_faces >> 6) & 63, (self.pos_faces >> 12) & 63]
    }

    pub fn faces(&self) -> u8 {
        ((self.pos_faces >> 18) & 63) as u8
    }

    /// Occupied fraction of the level-0 voxels below, in 255ths.
    pub fn coverage(&self) -> u8 {
        (self.pos_faces >> 24) as u8
    }

    /// sRGB8 colour, if the block has colour.
    pub fn color(&self) -> Option<[u8; 3]> {
        let [r, g, b, a] = self.color.to_le_bytes();
        (a != 0).then_some([r, g, b])
    }

    /// The precomputed AO field's byte (`1 + round(254·V)`), `None` when the
    /// block has none.
    pub fn field(&self) -> Option<u8> {
        let f = (self.normal >> 16) as u8;
        (f != 0).then_some(f)
    }

    /// Sets the AO field byte (0 = none).
    pub fn with_field(mut self, field: u8) -> Self {
        self.normal = (self.normal & 0xffff) | (field as u32) << 16;
        self
    }

    pub fn morton(&self) -> u32 {
        let [x, y, z] = self.local();
        morton3(x, y, z)
    }
}

/// Coverage byte for a level-`level` voxel with `count` occupied level-0
/// voxels below it: `round(255 · count / 8^level)`, but never 0 for a voxel
/// that exists (it covers something).
pub fn coverage_from_count(count: u64, level: u8) -> u8 {
    let cells = 1u64 << (3 * level as u32).min(63);
    if count >= cells {
        return 255; // every level-0 voxel: skip the float work
    }
    let x = (count as f64 / cells as f64) * 255.0;
    // `x.round()` without the libm call: x < 255, so its fraction is exact.
    let t = x as u64;
    let c = if x - t as f64 >= 0.5 { t + 1 } else { t } as u8;
    c.max(1)
}

/// A decoded block: voxels in strictly increasing Morton order of their local position.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Block {
    pub key: BlockKey,
    pub voxels: Vec<PackedVoxel>,
}

impl Block {
    /// Number of exposed faces, i.e. quads the renderer will draw.
    pub fn face_count(&self) -> u32 {
        self.voxels.iter().map(|v| v.faces().count_ones()).sum()
    }
}

fn spread3(v: u32) -> u32 {
    // Interleave the low 10 bits of v with two zero bits between each.
    let mut x = v & 0x3ff;
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    (x | (x << 2)) & 0x0924_9249
}

/// Morton (Z-order) index of a point with coordinates below 1024.
pub fn morton3(x: u32, y: u32, z: u32) -> u32 {
    spread3(x) | spread3(y) << 1 | spread3(z) << 2
}

fn squash3(v: u32) -> u32 {
    // Inverse of spread3: keep every third bit and pack them together.
    let mut x = v & 0x0924_9249;
    x = (x | (x >> 2)) & 0x030c_30c3;
    x = (x | (x >> 4)) & 0x0300_f00f;
    x = (x | (x >> 8)) & 0x0300_00ff;
    (x | (x >> 16)) & 0x3ff
}

/// Inverse of [`morton3`].
pub fn demorton3(m: u32) -> [u32; 3] {
    [squash3(m), squash3(m >> 1), squash3(m >> 2)]
}

fn snorm8(v: f32) -> u32 {
    (round_snorm(v.clamp(-1.0, 1.0) * 127.0) as i8) as u8 as u32
}

/// `x.round()` (half away from zero) for |x| ≤ 127, from float adds,
/// compares and a bit cast only, so the batch form ([`oct_encode_many`])
/// vectorizes fully (a float → int `as` stays scalar: it saturates).
/// Adding 1.5 · 2^23 leaves x rounded to the nearest integer, ties to even,
/// in the low mantissa bits (the sum's unit in the last place is 1); a tie
/// that went towards zero then moves one step away. Equal to `round` on
/// every float of [-127, 127] (checked exhaustively, 2,247,884,802 values,
/// 2026-11-24; the unit test samples around every half-integer). NaN gives
/// an unspecified value: `oct_encode` only keeps results of finite inputs.
#[inline]
fn round_snorm(x: f32) -> i32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5 · 2^23
    let r = (x + MAGIC).to_bits() as i32 - MAGIC.to_bits() as i32;
    let d = x - r as f32;
    r + i32::from(d == 0.5 && x > 0.0) - i32::from(d == -0.5 && x < 0.0)
}

fn unsnorm8(v: u32) -> f32 {
    ((v as u8) as i8 as f32 / 127.0).max(-1.0)
}

/// Octahedral encoding of a direction (need not be normalised) in two snorm8
/// halves (x in bits 0..8, y in bits 8..16): worst angular error about 0.8°
/// (measured in `oct_round_trip_is_accurate`), far below what voxel shading
/// shows. A zero or non-finite vector encodes as +Z so that every voxel has a
/// usable normal.
///
/// Two divisions, not a reciprocal and two products: the two divisions are
/// independent and pipeline, and a reciprocal version kept bit-identical (a
/// guard sending values within 1e-4 of a rounding boundary to the exact path)
/// measured no faster (1,800 against 1,802 perf samples on Cedar Creek at
/// 4096, notes/BENCHMARKS.md, 2026-11-24).
#[inline]
pub fn oct_encode(n: [f32; 3]) -> u32 {
    let l1 = n[0].abs() + n[1].abs() + n[2].abs();
    // Computed for every input and selected at the end: no branch to mispredict.
    let (mut u, mut v) = (n[0] / l1, n[1] / l1);
    // The lower hemisphere folds over: `(1 - |v|) · signum(u)`, written as
    // `copysign` (the same bits: `1 - |v|` is ≥ +0, and u, v are not NaN
    // when l1 is finite and positive).
    let below = n[2] < 0.0;
    let (fu, fv) = ((1.0 - v.abs()).copysign(u), (1.0 - u.abs()).copysign(v));
    u = if below { fu } else { u };
    v = if below { fv } else { v };
    let e = snorm8(u) | snorm8(v) << 8;
    if l1.is_finite() && l1 > 0.0 { e } else { OCT_PLUS_Z }
}

/// `oct_encode([0, 0, 1])`: the normal of a zero or non-finite sum.
const OCT_PLUS_Z: u32 = 0;

/// [`oct_encode`] of every normal, as u16 (the codec's column), appended to
/// `out`. Eight at a time through lane-wise arrays, which the compiler turns
/// into vector instructions; bit-identical to the scalar form (tested).
pub fn oct_encode_many(normals: impl ExactSizeIterator<Item = [f32; 3]>, out: &mut Vec<u16>) {
    const LANES: usize = 8;
    out.reserve(normals.len());
    let mut normals = normals.peekable();
    while normals.peek().is_some() {
        let mut n = [[0.0f32; LANES]; 3];
        let mut len = 0;
        for (i, v) in normals.by_ref().take(LANES).enumerate() {
            for a in 0..3 {
                n[a][i] = v[a];
            }
            len = i + 1;
        }
        let mut e = [0u16; LANES];
        for i in 0..LANES {
            e[i] = oct_encode([n[0][i], n[1][i], n[2][i]]) as u16;
        }
        out.extend_from_slice(&e[..len]);
    }
}

/// Inverse of [`oct_encode`]; returns a unit vector.
pub fn oct_decode(e: u32) -> [f32; 3] {
    let (u, v) = (unsnorm8(e & 0xff), unsnorm8(e >> 8));
    let z = 1.0 - u.abs() - v.abs();
    let t = (-z).max(0.0);
    let x = u - t * u.signum();
    let y = v - t * v.signum();
    let len = (x * x + y * y + z * z).sqrt();
    [x / len, y / len, z / len]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corners_wind_counter_clockwise_from_outside() {
        for face in Face::ALL {
            let c = face.corners([0.0; 3], 1.0);
            let e1: Vec<f64> = (0..3).map(|i| c[1][i] - c[0][i]).collect();
            let e2: Vec<f64> = (0..3).map(|i| c[2][i] - c[0][i]).collect();
            let n =
                [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
            assert_eq!(n[face.axis()].signum() as i32, face.sign(), "{face:?}");
        }
    }

    /// Fails if `round_snorm` differs from `f32::round` anywhere a snorm8 can
    /// land: every float of [-127, 127] around each half-integer and integer,
    /// and a dense sweep between.
    #[test]
    fn round_snorm_matches_round() {
        let check = |x: f32| assert_eq!(round_snorm(x), x.round() as i32, "{x:?}");
        for k in (-254i32..=254).filter(|&k| k != 0) {
            let mid = k as f32 * 0.5;
            let mut x = mid;
            for _ in 0..64 {
                x = f32::from_bits(x.to_bits() - 1);
            }
            for _ in 0..129 {
                check(x);
                x = f32::from_bits(x.to_bits() + 1);
            }
        }
        for i in 0..=2_000_000 {
            check(-127.0 + 254.0 * i as f32 / 2_000_000.0);
        }
        for x in [0.0f32, -0.0, 127.0, -127.0, 0.5, -0.5, 1.5, -1.5, 2.5, -2.5, 126.5, -126.5] {
            check(x);
        }
        // The control: truncation alone fails the halves.
        assert_ne!(2.5f32 as i32, 2.5f32.round() as i32);
    }

    /// Fails if the fast paths of `coverage_from_count` differ from the
    /// plain `round(255 · count / cells)` formula at any count of levels 0–4
    /// or at sampled counts of the deepest levels.
    #[test]
    fn coverage_matches_the_formula() {
        let plain = |count: u64, level: u8| {
            let cells = 1u64 << (3 * level as u32).min(63);
            (((count.min(cells) as f64 / cells as f64) * 255.0).round() as u8).max(1)
        };
        for level in 0..=4u8 {
            for count in 0..=(1u64 << (3 * level)) + 2 {
                assert_eq!(coverage_from_count(count, level), plain(count, level), "{count} at {level}");
            }
        }
        for level in 5..=21u8 {
            let cells = 1u64 << (3 * level as u32).min(63);
            for i in 0..=100_000u64 {
                let count = (cells as u128 * i as u128 / 100_000) as u64;
                for c in [count.saturating_sub(1), count, count + 1] {
                    assert_eq!(coverage_from_count(c, level), plain(c, level), "{c} at {level}");
                }
            }
        }
        // The control: half a step must round up, as round() does.
        assert_eq!(coverage_from_count(1, 1), plain(1, 1));
        assert_eq!(plain(1, 1), 32, "255/8 = 31.875");
    }

    #[test]
    fn morton_orders_octants() {
        assert_eq!(morton3(0, 0, 0), 0);
        assert_eq!(morton3(1, 0, 0), 1);
        assert_eq!(morton3(0, 1, 0), 2);
        assert_eq!(morton3(0, 0, 1), 4);
        assert_eq!(morton3(63, 63, 63), (1 << 18) - 1);
    }

    #[test]
    fn demorton_inverts_morton() {
        for p in [[0, 0, 0], [63, 0, 5], [17, 42, 63], [1023, 1, 512]] {
            assert_eq!(demorton3(morton3(p[0], p[1], p[2])), p);
        }
    }

    #[test]
    fn packed_fields_round_trip() {
        let v = PackedVoxel::new([63, 5, 17], 0b101101, 7);
        assert_eq!(v.local(), [63, 5, 17]);
        assert_eq!(v.faces(), 0b101101);
        assert_eq!(v.coverage(), FULL_COVERAGE);
        assert_eq!(v.color(), None);
        let v = v.with_coverage(9).with_color([1, 2, 250]);
        assert_eq!(
            (v.local(), v.faces(), v.coverage(), v.color()),
            ([63, 5, 17], 0b101101, 9, Some([1, 2, 250]))
        );
    }

    #[test]
    fn coverage_counts() {
        assert_eq!(coverage_from_count(1, 0), 255);
        assert_eq!(coverage_from_count(8, 1), 255);
        assert_eq!(coverage_from_count(4, 1), 128);
        assert_eq!(coverage_from_count(1, 5), 1, "an existing voxel never reads empty");
        assert_eq!(coverage_from_count(0, 2), 1);
    }

    /// The branching form `oct_encode` had before it was made branch-free: the reference.
    fn oct_encode_branching(n: [f32; 3]) -> u32 {
        fn round(x: f32) -> i32 {
            let t = x as i32;
            let frac = x - t as f32;
            if frac >= 0.5 {
                t + 1
            } else if frac <= -0.5 {
                t - 1
            } else {
                t
            }
        }
        let snorm = |v: f32| (round(v.clamp(-1.0, 1.0) * 127.0) as i8) as u8 as u32;
        let l1 = n[0].abs() + n[1].abs() + n[2].abs();
        if !(l1.is_finite() && l1 > 0.0) {
            return oct_encode_branching([0.0, 0.0, 1.0]);
        }
        let (mut u, mut v) = (n[0] / l1, n[1] / l1);
        if n[2] < 0.0 {
            let (pu, pv) = (u, v);
            u = (1.0 - pv.abs()) * pu.signum();
            v = (1.0 - pu.abs()) * pv.signum();
        }
        snorm(u) | snorm(v) << 8
    }

    /// Fails if the branch-free `oct_encode` or `oct_encode_many` differs from
    /// the branching form anywhere: special values (zeros of both signs, NaN,
    /// infinities, subnormals, extremes) in every combination, random bit
    /// patterns, random directions, and normals whose snorm8 lands within a
    /// few ulps of a rounding boundary.
    #[test]
    fn oct_encode_is_the_branching_form() {
        let special = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            0.5,
            -0.5,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x8000_0001),
            f32::MAX,
            f32::MIN,
            1e-30,
            3.0e30,
        ];
        let mut inputs = Vec::new();
        for &x in &special {
            for &y in &special {
                for &z in &special {
                    inputs.push([x, y, z]);
                }
            }
        }
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..300_000 {
            let r = next();
            inputs.push([r as u32, (r >> 32) as u32, next() as u32].map(f32::from_bits));
            let d = [next(), next(), next()].map(|r| (r >> 40) as f32 / (1u64 << 23) as f32 - 1.0);
            inputs.push(d);
        }
        // u = x / l1 with 127·u near k + 0.5: x = (k + 0.5) / 127 · l1, nudged by ulps.
        for k in -127i32..127 {
            let u = (k as f32 + 0.5) / 127.0;
            for z in [0.25f32, -0.25, 0.7, -0.7] {
                let rest = 1.0 - u.abs();
                let y = rest - z.abs().min(rest);
                let x0 = u;
                for d in -4i32..=4 {
                    let x = f32::from_bits((x0.to_bits() as i32 + d) as u32);
                    inputs.push([x, y, z]);
                    inputs.push([y, x, z]);
                }
            }
        }
        for n in &inputs {
            assert_eq!(oct_encode(*n), oct_encode_branching(*n), "{n:?}");
        }
        for len in [0, 1, 7, 8, 9, inputs.len()] {
            let mut got = vec![5u16];
            oct_encode_many(inputs[..len].iter().copied(), &mut got);
            let want: Vec<u16> = std::iter::once(5)
                .chain(inputs[..len].iter().map(|n| oct_encode_branching(*n) as u16))
                .collect();
            assert_eq!(got, want, "batch of {len}");
        }
    }

    #[test]
    fn oct_round_trip_is_accurate() {
        let mut worst: f32 = 1.0;
        for i in 0..20000 {
            let t = i as f32 * 0.731;
            let p = (i as f32 * 0.377).sin();
            let n = [t.cos() * (1.0 - p * p).sqrt(), t.sin() * (1.0 - p * p).sqrt(), p];
            let d = oct_decode(oct_encode(n));
            worst = worst.min(n[0] * d[0] + n[1] * d[1] + n[2] * d[2]);
        }
        let degrees = worst.min(1.0).acos().to_degrees();
        // snorm8 octahedral: measured worst case about 0.8 degrees.
        assert!(degrees < 1.0, "worst angular error {degrees} degrees");
        assert!(degrees > 0.1, "8-bit quantisation cannot be this exact: {degrees}");
        assert_eq!(oct_encode([1.0, 2.0, 3.0]) >> 16, 0);
        assert_eq!(oct_decode(oct_encode([0.0, 0.0, 0.0])), [0.0, 0.0, 1.0]);
        assert_eq!(oct_decode(oct_encode([f32::NAN, 0.0, 1.0])), [0.0, 0.0, 1.0]);
    }

    #[test]
    fn face_bits_and_axes() {
        let mask: u8 = Face::ALL.iter().map(|f| f.bit()).sum();
        assert_eq!(mask, 63);
        assert_eq!(Face::PosY.axis(), 1);
        assert_eq!(Face::PosY.sign(), 1);
        assert_eq!(Face::NegZ.sign(), -1);
    }
}
