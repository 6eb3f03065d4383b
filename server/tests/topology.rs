//! Output topology (Laine's targets, seed 003 §3.1.2): the 6- and 26-separating
//! sets block every 6- and 26-connected path through closed meshes, and
//! 6-separating ⊆ 26-separating ⊆ conservative.

use std::collections::{BTreeSet, VecDeque};
use std::f64::consts::PI;
use std::path::Path;

use proptest::prelude::*;
use voxstream::pipeline::progress::ProgressSink;
use voxstream::pipeline::pyramid::local_position;
use voxstream::pipeline::read::{TriangleMesh, read_mesh};
use voxstream::pipeline::voxelize::{Topology, choose_frame, voxelize_reporting};
use voxstream_format::{BLOCK_SIZE, GridFrame};

fn voxel_set(mesh: &TriangleMesh, frame: &GridFrame, topology: Topology) -> BTreeSet<[i64; 3]> {
    let (blocks, _) = voxelize_reporting(mesh, frame, topology, &ProgressSink::new(&|_| {})).unwrap();
    let mut set = BTreeSet::new();
    for b in &blocks {
        for v in &b.voxels {
            let p = local_position(v);
            set.insert(std::array::from_fn(|a| (b.key.coord()[a] * BLOCK_SIZE + p[a]) as i64));
        }
    }
    set
}

/// A dense boolean grid over the voxel grid padded by one layer on each side.
struct Dense {
    res: i64,
    cells: Vec<bool>,
}

impl Dense {
    fn new(res: i64) -> Self {
        Self { res, cells: vec![false; ((res + 2) * (res + 2) * (res + 2)) as usize] }
    }
    fn index(&self, p: [i64; 3]) -> Option<usize> {
        let n = self.res + 2;
        let q = p.map(|c| c + 1);
        q.iter().all(|&c| (0..n).contains(&c)).then(|| ((q[2] * n + q[1]) * n + q[0]) as usize)
    }
    fn from_set(set: &BTreeSet<[i64; 3]>, res: i64) -> Self {
        let mut d = Dense::new(res);
        for &p in set {
            let i = d.index(p).unwrap();
            d.cells[i] = true;
        }
        d
    }
    fn get(&self, p: [i64; 3]) -> bool {
        self.index(p).is_some_and(|i| self.cells[i])
    }
}

/// Voxels reachable from outside the grid through voxels not in `wall`,
/// stepping to 6 or 26 neighbours. The padding layer keeps the outside connected.
fn reachable(wall: &BTreeSet<[i64; 3]>, res: i64, neighbours: usize) -> Dense {
    let wall = Dense::from_set(wall, res);
    let steps: Vec<[i64; 3]> = (-1..=1)
        .flat_map(|x| (-1..=1).flat_map(move |y| (-1..=1).map(move |z| [x, y, z])))
        .filter(|d: &[i64; 3]| {
            let n = d.iter().filter(|&&c| c != 0).count();
            n > 0 && (neighbours == 26 || n == 1)
        })
        .collect();
    let mut seen = Dense::new(res);
    let start = [-1i64, -1, -1];
    let i = seen.index(start).unwrap();
    seen.cells[i] = true;
    let mut queue = VecDeque::from([start]);
    while let Some(p) = queue.pop_front() {
        for d in &steps {
            let q = [p[0] + d[0], p[1] + d[1], p[2] + d[2]];
            let Some(i) = seen.index(q) else { continue };
            if seen.cells[i] || wall.cells[i] {
                continue;
            }
            seen.cells[i] = true;
            queue.push_back(q);
        }
    }
    seen
}

/// Voxels strictly inside: cut off from outside by the conservative set, and
/// not touching the surface themselves.
fn strictly_inside(conservative: &BTreeSet<[i64; 3]>, res: i64) -> Vec<[i64; 3]> {
    let outside = reachable(conservative, res, 26);
    let mut inside = Vec::new();
    for x in 0..res {
        for y in 0..res {
            for z in 0..res {
                let p = [x, y, z];
                if !conservative.contains(&p) && !outside.get(p) {
                    inside.push(p);
                }
            }
        }
    }
    inside
}

struct Checked {
    inside: usize,
    sizes: [usize; 3],
    leak_6sep_26path: bool,
}

fn check_closed_mesh(mesh: &TriangleMesh, frame: &GridFrame) -> Checked {
    let res = frame.resolution as i64;
    let cons = voxel_set(mesh, frame, Topology::Conservative);
    let s26 = voxel_set(mesh, frame, Topology::Separating26);
    let s6 = voxel_set(mesh, frame, Topology::Separating6);
    assert!(s6.is_subset(&s26), "6-separating ⊄ 26-separating");
    assert!(s26.is_subset(&cons), "26-separating ⊄ conservative");
    let inside = strictly_inside(&cons, res);
    for (set, neighbours, name) in [(&s26, 26, "26"), (&s6, 6, "6")] {
        let reach = reachable(set, res, neighbours);
        let leaked: Vec<_> = inside.iter().filter(|p| reach.get(**p)).take(3).collect();
        assert!(
            leaked.is_empty(),
            "a {name}-connected path leaks through the {name}-separating set to {leaked:?}"
        );
    }
    let reach = reachable(&s6, res, 26);
    Checked {
        inside: inside.len(),
        sizes: [cons.len(), s26.len(), s6.len()],
        leak_6sep_26path: inside.iter().any(|p| reach.get(*p)),
    }
}

fn grid(res: u32) -> GridFrame {
    GridFrame { origin: [0.0; 3], voxel_size: 1.0, resolution: res, units: None }
}

/// A closed UV sphere (poles shared) or torus, in grid units.
fn closed_mesh(kind: u8, centre: [f64; 3], r: f64, r2: f64, seg: u32) -> TriangleMesh {
    let mut m = TriangleMesh::default();
    let (rows, cols) = (seg, 2 * seg);
    let at = |u: f64, v: f64| -> [f64; 3] {
        if kind == 0 {
            let (t, p) = (PI * u, 2.0 * PI * v);
            [centre[0] + r * t.sin() * p.cos(), centre[1] + r * t.cos(), centre[2] + r * t.sin() * p.sin()]
        } else {
            let (a, b) = (2.0 * PI * u, 2.0 * PI * v);
            let ring = r + r2 * a.cos();
            [centre[0] + ring * b.cos(), centre[1] + r2 * a.sin(), centre[2] + ring * b.sin()]
        }
    };
    // Vertices on a (rows+1)×cols lattice; seams are shared by index so the mesh is closed.
    for i in 0..=rows {
        for j in 0..cols {
            m.positions.push(at(i as f64 / rows as f64, j as f64 / cols as f64));
        }
    }
    let idx = |i: u32, j: u32| {
        let i = if kind == 1 { i % rows } else { i };
        i * cols + j % cols
    };
    for i in 0..rows {
        for j in 0..cols {
            let (a, b, c, d) = (idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1));
            m.triangles.push([a, c, b]);
            m.triangles.push([b, c, d]);
        }
    }
    if kind == 0 {
        // Collapse each pole ring to one vertex so no sliver gap remains.
        let (top, bottom) = (0u32, rows * cols);
        for t in &mut m.triangles {
            for v in t.iter_mut() {
                if *v < cols {
                    *v = top;
                } else if *v >= rows * cols {
                    *v = bottom;
                }
            }
        }
    }
    m
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, .. ProptestConfig::default() })]

    #[test]
    fn spheres_and_tori_are_sealed(
        kind in 0u8..2,
        // Kept inside the 64³ grid: r + r2 < 26 and the centre within 30..34.
        cx in 30.0f64..34.0, cy in 30.0f64..34.0, cz in 30.0f64..34.0,
        r in 8.0f64..16.0, r2_frac in 0.3f64..0.6,
        seg in 6u32..40,
    ) {
        let mesh = closed_mesh(kind, [cx, cy, cz], r, r * r2_frac, seg);
        let checked = check_closed_mesh(&mesh, &grid(64));
        prop_assert!(checked.inside > 0, "no interior found: the test would prove nothing");
    }
}

#[test]
fn separating_sets_are_thinner_and_the_check_can_fail() {
    let mesh = closed_mesh(0, [31.7, 32.2, 30.9], 22.0, 0.0, 48);
    let c = check_closed_mesh(&mesh, &grid(64));
    let [cons, s26, s6] = c.sizes;
    assert!(s26 < cons && s6 < s26, "sizes {:?}", c.sizes);
    // The 6-separating set is thin enough that 26-connected paths slip through
    // its diagonal gaps: the flood fill does detect leaks.
    assert!(c.leak_6sep_26path, "expected the 6-separating sphere to leak to 26-connected paths");
}

#[test]
fn closed_koala_is_sealed() {
    let (mesh, _) = read_mesh(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj")).unwrap();
    let frame = choose_frame(&mesh, 64).unwrap();
    let c = check_closed_mesh(&mesh, &frame);
    assert!(c.inside > 500, "the koala should enclose a solid interior, found {} voxels", c.inside);
}
