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
}

/// A voxel as stored in a block and as read by the GPU: 8 bytes.
///
/// `pos_faces` = `x | y << 6 | z << 12 | faces << 18` (x, y, z < 64, block-local);
/// `normal` = octahedral-encoded unit normal, two snorm16 halves (x low, y high).
/// Bits 24..32 of `pos_faces` are zero in every valid voxel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable, Default)]
#[repr(C)]
pub struct PackedVoxel {
    pub pos_faces: u32,
    pub normal: u32,
}

impl PackedVoxel {
    pub fn new(local: [u32; 3], faces: u8, normal: u32) -> Self {
        debug_assert!(local.iter().all(|&c| c < BLOCK_SIZE) && faces < 64);
        Self { pos_faces: local[0] | local[1] << 6 | local[2] << 12 | (faces as u32) << 18, normal }
    }

    pub fn local(&self) -> [u32; 3] {
        [self.pos_faces & 63, (self.pos_faces >> 6) & 63, (self.pos_faces >> 12) & 63]
    }

    pub fn faces(&self) -> u8 {
        ((self.pos_faces >> 18) & 63) as u8
    }

    pub fn morton(&self) -> u32 {
        let [x, y, z] = self.local();
        morton3(x, y, z)
    }
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

fn snorm16(v: f32) -> u32 {
    ((v.clamp(-1.0, 1.0) * 32767.0).round() as i16) as u16 as u32
}

fn unsnorm16(v: u32) -> f32 {
    ((v as u16) as i16 as f32 / 32767.0).max(-1.0)
}

/// Octahedral encoding of a direction (need not be normalised). A zero or
/// non-finite vector encodes as +Z so that every voxel has a usable normal.
pub fn oct_encode(n: [f32; 3]) -> u32 {
    let l1 = n[0].abs() + n[1].abs() + n[2].abs();
    if !(l1.is_finite() && l1 > 0.0) {
        return oct_encode([0.0, 0.0, 1.0]);
    }
    let (mut u, mut v) = (n[0] / l1, n[1] / l1);
    if n[2] < 0.0 {
        let (pu, pv) = (u, v);
        u = (1.0 - pv.abs()) * pu.signum();
        v = (1.0 - pu.abs()) * pv.signum();
    }
    snorm16(u) | snorm16(v) << 16
}

/// Inverse of [`oct_encode`]; returns a unit vector.
pub fn oct_decode(e: u32) -> [f32; 3] {
    let (u, v) = (unsnorm16(e & 0xffff), unsnorm16(e >> 16));
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
        assert_eq!(v.pos_faces >> 24, 0);
    }

    #[test]
    fn oct_round_trip_is_accurate() {
        let mut worst: f32 = 1.0;
        for i in 0..2000 {
            let t = i as f32 * 0.731;
            let p = (i as f32 * 0.377).sin();
            let n = [t.cos() * (1.0 - p * p).sqrt(), t.sin() * (1.0 - p * p).sqrt(), p];
            let d = oct_decode(oct_encode(n));
            worst = worst.min(n[0] * d[0] + n[1] * d[1] + n[2] * d[2]);
        }
        // cos of the worst angular error; snorm16 keeps it far below 0.01 degrees.
        assert!(worst > 0.999_999, "worst dot {worst}");
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
