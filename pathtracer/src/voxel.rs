//! Surface voxelisation of triangle meshes: the occupancy that the perfect spatial hash
//! and the benchmarks use when a mesh (a built-in scene) is at hand instead of a trained
//! density field.

use glam::Vec3;

use crate::Mesh;

/// A cubic voxel grid: `res^3` voxels of side `voxel`, starting at `min`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelGrid {
    pub min: Vec3,
    pub voxel: f32,
    pub res: u32,
}

impl VoxelGrid {
    /// The grid of side `res` that holds the box `[lo, hi]` (its longest side, plus half a
    /// voxel of margin on each side so that surfaces on the box faces are inside).
    pub fn around(lo: Vec3, hi: Vec3, res: u32) -> VoxelGrid {
        let res = res.max(1);
        let side = (hi - lo).max_element().max(1e-6);
        let voxel = side / (res as f32 - 1.0).max(1.0);
        let center = 0.5 * (lo + hi);
        VoxelGrid { min: center - Vec3::splat(0.5 * voxel * res as f32), voxel, res }
    }

    /// Voxel holding a point, if inside.
    pub fn voxel_of(&self, p: Vec3) -> Option<[u32; 3]> {
        let f = (p - self.min) / self.voxel;
        let r = self.res as f32;
        (f.cmpge(Vec3::ZERO).all() && f.cmplt(Vec3::splat(r)).all())
            .then(|| [(f.x as u32).min(self.res - 1), (f.y as u32).min(self.res - 1), (f.z as u32).min(self.res - 1)])
    }
}

/// A set of voxels of a [`VoxelGrid`] as a bit array.
#[derive(Debug, Clone, PartialEq)]
pub struct VoxelBits {
    pub grid: VoxelGrid,
    bits: Vec<u64>,
}

impl VoxelBits {
    /// Whether the voxel holding `p` is set (false outside the grid).
    pub fn contains(&self, p: Vec3) -> bool {
        self.grid.voxel_of(p).is_some_and(|v| self.get(v))
    }

    pub fn get(&self, v: [u32; 3]) -> bool {
        let res = self.grid.res as usize;
        let idx = v[0] as usize + res * (v[1] as usize + res * v[2] as usize);
        self.bits.get(idx / 64).is_some_and(|w| w >> (idx % 64) & 1 == 1)
    }

    /// Set voxels sorted by packed key (z, y, x).
    pub fn points(&self) -> Vec<[u32; 3]> {
        let res = self.grid.res as usize;
        let mut out = Vec::new();
        for (w, &word) in self.bits.iter().enumerate() {
            let mut word = word;
            while word != 0 {
                let idx = w * 64 + word.trailing_zeros() as usize;
                word &= word - 1;
                out.push([(idx % res) as u32, ((idx / res) % res) as u32, (idx / (res * res)) as u32]);
            }
        }
        out
    }
}

/// Voxels of `grid` touched by the triangles of `mesh`, sorted by packed key (z, y, x) and
/// without duplicates. Triangles are sampled on a barycentric lattice finer than half a
/// voxel, which finds every voxel the surface crosses by more than a sliver.
pub fn surface_voxels(mesh: &Mesh, grid: &VoxelGrid) -> Vec<[u32; 3]> {
    surface_bits(mesh, grid).points()
}

/// Calls `visit` with points of every finite triangle of `mesh` on a barycentric lattice at
/// most `step` apart along the longest edge (at most 4096 steps per edge).
fn for_surface_points(mesh: &Mesh, step: f32, mut visit: impl FnMut(Vec3)) {
    for tri in &mesh.indices {
        let [a, b, c] = tri.map(|i| mesh.positions.get(i as usize).copied().unwrap_or(Vec3::NAN));
        if !(a.is_finite() && b.is_finite() && c.is_finite()) {
            continue;
        }
        let longest = (b - a).length().max((c - a).length()).max((c - b).length());
        let n = ((longest / step).ceil() as usize).clamp(1, 4096);
        for i in 0..=n {
            for j in 0..=(n - i) {
                visit(a + (b - a) * (i as f32 / n as f32) + (c - a) * (j as f32 / n as f32));
            }
        }
    }
}

/// [`surface_voxels`] as a bit array.
pub fn surface_bits(mesh: &Mesh, grid: &VoxelGrid) -> VoxelBits {
    let res = grid.res as usize;
    let mut bits = vec![0u64; (res * res * res).div_ceil(64)];
    let step = 0.5 * grid.voxel;
    for_surface_points(mesh, step, |p| {
        if let Some([x, y, z]) = grid.voxel_of(p) {
            let idx = x as usize + res * (y as usize + res * z as usize);
            bits[idx / 64] |= 1 << (idx % 64);
        }
    });
    VoxelBits { grid: *grid, bits }
}

/// A coarse occupancy of a mesh over the box `[min, max]`: `dims` cells per axis (x fastest),
/// the longest axis cut into `longest_cells`, and `true` in every cell that the surface passes
/// within `margin` cells of (a margin of 0.5 also takes in the slivers that sampling misses and
/// the half-cell blur of a field baked from the mesh). The TaskAssigner's proxy of an object
/// (NEPHELE's prior mesh, section 5): its projection bounds the pixels the object covers.
pub fn cell_occupancy(mesh: &Mesh, min: Vec3, max: Vec3, longest_cells: u32, margin: f32) -> ([u32; 3], Vec<bool>) {
    let size = (max - min).max(Vec3::splat(1e-6));
    let cell = size.max_element() / longest_cells.max(1) as f32;
    let dims = (size / cell).ceil().max(Vec3::ONE);
    let dims = [dims.x as u32, dims.y as u32, dims.z as u32];
    // Cells of equal side along every axis, the last one of each axis reaching `max`.
    let step = size / Vec3::new(dims[0] as f32, dims[1] as f32, dims[2] as f32);
    let mut occupied = vec![false; dims.iter().map(|&d| d as usize).product()];
    let reach = Vec3::splat(margin.max(0.0));
    let sample_step = 0.5 * step.min_element();
    for_surface_points(mesh, sample_step, |p| {
        let f = (p - min) / step;
        let lo = (f - reach).floor().max(Vec3::ZERO);
        let hi = (f + reach).floor();
        for z in lo.z as u32..=(hi.z.max(0.0) as u32).min(dims[2] - 1) {
            for y in lo.y as u32..=(hi.y.max(0.0) as u32).min(dims[1] - 1) {
                for x in lo.x as u32..=(hi.x.max(0.0) as u32).min(dims[0] - 1) {
                    let index = x as usize + dims[0] as usize * (y as usize + dims[1] as usize * z as usize);
                    occupied[index] = true;
                }
            }
        }
    });
    (dims, occupied)
}

/// The cells of the box `[min, max]` (cut as [`cell_occupancy`] cuts it) that lie wholly inside
/// the matter of a closed mesh: not within `margin` cells of its surface, and walled off from
/// the box's faces by surface cells (a flood fill from the faces through the cells the surface
/// does not touch reaches every other cell). A gap in the surface, or a mesh that is not
/// closed, only makes fewer cells solid. What the environment kernel skips the lighting behind
/// (`nephele_geometry::SolidGrid`).
pub fn solid_cells(mesh: &Mesh, min: Vec3, max: Vec3, longest_cells: u32, margin: f32) -> ([u32; 3], Vec<bool>) {
    let (dims, near_surface) = cell_occupancy(mesh, min, max, longest_cells, margin);
    let [nx, ny, nz] = dims.map(|d| d as usize);
    let index = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
    let mut outside = vec![false; near_surface.len()];
    let mut stack = Vec::new();
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let on_face = x == 0 || y == 0 || z == 0 || x + 1 == nx || y + 1 == ny || z + 1 == nz;
                let i = index(x, y, z);
                if on_face && !near_surface[i] && !outside[i] {
                    outside[i] = true;
                    stack.push((x, y, z));
                }
            }
        }
    }
    while let Some((x, y, z)) = stack.pop() {
        let neighbours = [
            (x.wrapping_sub(1), y, z),
            (x + 1, y, z),
            (x, y.wrapping_sub(1), z),
            (x, y + 1, z),
            (x, y, z.wrapping_sub(1)),
            (x, y, z + 1),
        ];
        for (a, b, c) in neighbours {
            if a < nx && b < ny && c < nz {
                let i = index(a, b, c);
                if !near_surface[i] && !outside[i] {
                    outside[i] = true;
                    stack.push((a, b, c));
                }
            }
        }
    }
    let solid = near_surface.iter().zip(&outside).map(|(&surface, &out)| !surface && !out).collect();
    (dims, solid)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The square z = 0.5 spanning the unit box.
    fn square_at_half_height() -> Mesh {
        Mesh::new(
            vec![
                Vec3::new(0.0, 0.0, 0.5),
                Vec3::new(1.0, 0.0, 0.5),
                Vec3::new(1.0, 1.0, 0.5),
                Vec3::new(0.0, 1.0, 0.5),
            ],
            vec![[0, 1, 2], [0, 2, 3]],
        )
    }

    #[test]
    fn cell_occupancy_marks_the_cells_a_surface_crosses_and_a_margin() {
        // The square z = 0.5 spanning the unit box, cut into 8 cells a side: the layer of
        // cells it lies on (z index 4; 0.5 is exactly their lower face, so with no margin
        // only that layer), then with half a cell of margin the layer below too.
        let mesh = square_at_half_height();
        let (dims, tight) = cell_occupancy(&mesh, Vec3::ZERO, Vec3::ONE, 8, 0.0);
        assert_eq!(dims, [8, 8, 8]);
        let layers =
            |cells: &[bool]| (0..8).filter(|z| cells[64 * z..64 * (z + 1)].iter().all(|&c| c)).collect::<Vec<usize>>();
        assert_eq!(tight.iter().filter(|&&c| c).count(), 64);
        assert_eq!(layers(&tight), vec![4]);
        let (_, loose) = cell_occupancy(&mesh, Vec3::ZERO, Vec3::ONE, 8, 0.5);
        assert_eq!(layers(&loose), vec![3, 4]);
        assert_eq!(loose.iter().filter(|&&c| c).count(), 128);
        // A flat box: the short axis gets fewer cells of the same side.
        let (dims, _) = cell_occupancy(&mesh, Vec3::ZERO, Vec3::new(1.0, 1.0, 0.25), 8, 0.0);
        assert_eq!(dims, [8, 8, 2]);
    }

    /// A closed axis-aligned box `[lo, hi]`, faces outward.
    fn box_mesh(lo: Vec3, hi: Vec3) -> Mesh {
        let p = |x: bool, y: bool, z: bool| {
            Vec3::new(if x { hi.x } else { lo.x }, if y { hi.y } else { lo.y }, if z { hi.z } else { lo.z })
        };
        let positions = vec![
            p(false, false, false),
            p(true, false, false),
            p(true, true, false),
            p(false, true, false),
            p(false, false, true),
            p(true, false, true),
            p(true, true, true),
            p(false, true, true),
        ];
        let quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [1, 2, 6, 5], [0, 4, 7, 3]];
        let indices = quads.iter().flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]).collect();
        Mesh::new(positions, indices)
    }

    #[test]
    fn solid_cells_are_the_inside_of_a_closed_mesh_less_a_margin() {
        // A closed box [0.2, 0.8]^3 in the unit box cut into 10 cells a side (0.1 each): its
        // faces lie on cell boundaries 2 and 8; half a cell of margin marks the layers on
        // both sides, cells 1-2 and 7-8, so cells 3-6 of each axis are solid: 4^3 = 64.
        let mesh = box_mesh(Vec3::splat(0.2), Vec3::splat(0.8));
        let (dims, solid) = solid_cells(&mesh, Vec3::ZERO, Vec3::ONE, 10, 0.5);
        assert_eq!(dims, [10, 10, 10]);
        assert_eq!(solid.iter().filter(|&&s| s).count(), 64);
        for z in 0..10 {
            for y in 0..10 {
                for x in 0..10 {
                    let inner = [x, y, z].iter().all(|c| (3..=6).contains(c));
                    assert_eq!(solid[x + 10 * (y + 10 * z)], inner, "cell {x} {y} {z}");
                }
            }
        }
        // Open it (drop the top face): the flood reaches in and nothing is solid.
        let open = Mesh::new(mesh.positions.clone(), mesh.indices[..10].to_vec());
        let (_, solid) = solid_cells(&open, Vec3::ZERO, Vec3::ONE, 10, 0.5);
        assert!(solid.iter().all(|&s| !s));
        // A flat square encloses nothing.
        let (_, solid) = solid_cells(&square_at_half_height(), Vec3::ZERO, Vec3::ONE, 8, 0.5);
        assert!(solid.iter().all(|&s| !s));
    }

    #[test]
    fn a_square_covers_one_layer() {
        // The square z = 0.5 spanning the unit box: one full layer of voxels.
        let mesh = square_at_half_height();
        let grid = VoxelGrid { min: Vec3::ZERO, voxel: 0.125, res: 8 };
        let v = surface_voxels(&mesh, &grid);
        assert_eq!(v.len(), 64);
        assert!(v.iter().all(|p| p[2] == 4));
    }
}
