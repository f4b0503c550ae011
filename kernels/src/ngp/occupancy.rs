//! The occupancy grid: one bit per cell of a regular grid over the field's box, set where
//! the density may be non-negligible, so that ray marching skips empty space (i-NGP,
//! section 5.4 / appendix E.2). A second, coarse level (one bit per 8^3 block) lets a ray
//! cross large empty regions in a few steps.
//!
//! Also here: the visual hull of a set of posed images with alpha, which bounds where
//! matter can be at all (a cell whose footprint is transparent in any view where it is
//! fully visible is empty). Training starts from it instead of from a full grid, which on a
//! CPU saves most of the early samples.

use glam::Vec3;

use nephele_geometry::camera::Camera;
use nephele_imaging::image::RgbaImage;

/// Cells per side of one coarse block.
pub const BLOCK: u32 = 8;

/// Bits over a `resolution^3` grid of the unit cube, with a coarse summary.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OccupancyGrid {
    resolution: u32,
    bits: Vec<u64>,
    coarse: Vec<u64>,
}

fn words(cells: usize) -> usize {
    cells.div_ceil(64)
}

impl OccupancyGrid {
    /// Smallest and largest supported resolution (multiples of [`BLOCK`]).
    pub const MIN_RESOLUTION: u32 = 16;
    pub const MAX_RESOLUTION: u32 = 512;

    /// Whether `resolution` is supported.
    pub fn valid_resolution(resolution: u32) -> bool {
        (Self::MIN_RESOLUTION..=Self::MAX_RESOLUTION).contains(&resolution) && resolution.is_multiple_of(BLOCK)
    }

    /// Number of `u64` words of the fine bits at `resolution`.
    pub fn word_count(resolution: u32) -> usize {
        words((resolution as usize).pow(3))
    }

    /// A grid with every cell `occupied` (or none). `resolution` must be valid.
    pub fn filled(resolution: u32, occupied: bool) -> Self {
        debug_assert!(Self::valid_resolution(resolution));
        let cells = (resolution as usize).pow(3);
        let mut bits = vec![if occupied { u64::MAX } else { 0 }; words(cells)];
        if occupied
            && !cells.is_multiple_of(64)
            && let Some(last) = bits.last_mut()
        {
            *last = (1u64 << (cells % 64)) - 1;
        }
        let mut grid = OccupancyGrid { resolution, bits, coarse: Vec::new() };
        grid.rebuild_coarse();
        grid
    }

    /// A grid from stored words (see [`OccupancyGrid::words`]); `None` if the count is wrong
    /// or the resolution invalid.
    pub fn from_words(resolution: u32, bits: Vec<u64>) -> Option<Self> {
        if !Self::valid_resolution(resolution) || bits.len() != Self::word_count(resolution) {
            return None;
        }
        let mut grid = OccupancyGrid { resolution, bits, coarse: Vec::new() };
        // Clear padding bits past the last cell so that counts are exact.
        let cells = (resolution as usize).pow(3);
        if !cells.is_multiple_of(64)
            && let Some(last) = grid.bits.last_mut()
        {
            *last &= (1u64 << (cells % 64)) - 1;
        }
        grid.rebuild_coarse();
        Some(grid)
    }

    /// A grid from one flag per cell (index `x + r * (y + r * z)`).
    pub fn from_flags(resolution: u32, flags: &[bool]) -> Option<Self> {
        if !Self::valid_resolution(resolution) || flags.len() != (resolution as usize).pow(3) {
            return None;
        }
        let mut bits = vec![0u64; words(flags.len())];
        for (i, _) in flags.iter().enumerate().filter(|(_, f)| **f) {
            bits[i / 64] |= 1 << (i % 64);
        }
        let mut grid = OccupancyGrid { resolution, bits, coarse: Vec::new() };
        grid.rebuild_coarse();
        Some(grid)
    }

    pub fn resolution(&self) -> u32 {
        self.resolution
    }

    /// The fine bits, 64 cells per word, cell `x + r * (y + r * z)` at bit `i % 64` of word
    /// `i / 64`.
    pub fn words(&self) -> &[u64] {
        &self.bits
    }

    pub fn cell_count(&self) -> usize {
        (self.resolution as usize).pow(3)
    }

    pub fn occupied_count(&self) -> usize {
        self.bits.iter().map(|w| w.count_ones() as usize).sum()
    }

    /// Index of cell `(x, y, z)`.
    #[inline]
    pub fn index(&self, x: u32, y: u32, z: u32) -> usize {
        let r = self.resolution as usize;
        x as usize + r * (y as usize + r * z as usize)
    }

    /// Centre of cell `index` in unit-cube coordinates.
    pub fn cell_center(&self, index: usize) -> Vec3 {
        let r = self.resolution as usize;
        let (x, y, z) = (index % r, (index / r) % r, index / (r * r));
        (Vec3::new(x as f32, y as f32, z as f32) + 0.5) / self.resolution as f32
    }

    #[inline]
    pub fn get(&self, index: usize) -> bool {
        self.bits[index / 64] >> (index % 64) & 1 == 1
    }

    /// Sets one cell; call [`OccupancyGrid::rebuild_coarse`] after a batch of changes.
    #[inline]
    pub fn set(&mut self, index: usize, occupied: bool) {
        if occupied {
            self.bits[index / 64] |= 1 << (index % 64);
        } else {
            self.bits[index / 64] &= !(1 << (index % 64));
        }
    }

    /// Recomputes the coarse level from the fine bits.
    pub fn rebuild_coarse(&mut self) {
        let blocks = self.resolution / BLOCK;
        let mut coarse = vec![0u64; words((blocks as usize).pow(3))];
        let r = self.resolution;
        for z in 0..r {
            for y in 0..r {
                let row = self.index(0, y, z);
                for x in 0..r {
                    if self.get(row + x as usize) {
                        let b = (x / BLOCK) as usize
                            + blocks as usize * ((y / BLOCK) as usize + blocks as usize * (z / BLOCK) as usize);
                        coarse[b / 64] |= 1 << (b % 64);
                    }
                }
            }
        }
        self.coarse = coarse;
    }

    /// The coarse level: one bit per block of [`BLOCK`]^3 cells, block `x + b (y + b z)`
    /// (`b = resolution / BLOCK`) at bit `i % 64` of word `i / 64`.
    pub fn coarse_words(&self) -> &[u64] {
        &self.coarse
    }

    /// Whether the coarse block holding cell `(x, y, z)` has any occupied cell.
    #[inline]
    pub fn block_occupied(&self, x: u32, y: u32, z: u32) -> bool {
        let blocks = (self.resolution / BLOCK) as usize;
        let b = (x / BLOCK) as usize + blocks * ((y / BLOCK) as usize + blocks * (z / BLOCK) as usize);
        self.coarse[b / 64] >> (b % 64) & 1 == 1
    }

    /// Bounding box of the occupied cells in unit-cube coordinates, `None` if none is.
    pub fn occupied_bounds(&self) -> Option<(Vec3, Vec3)> {
        let r = self.resolution;
        let (mut lo, mut hi) = ([u32::MAX; 3], [0u32; 3]);
        let mut any = false;
        for z in 0..r {
            for y in 0..r {
                for x in 0..r {
                    if self.get(self.index(x, y, z)) {
                        any = true;
                        for (d, v) in [x, y, z].into_iter().enumerate() {
                            lo[d] = lo[d].min(v);
                            hi[d] = hi[d].max(v + 1);
                        }
                    }
                }
            }
        }
        any.then(|| {
            let s = r as f32;
            (
                Vec3::new(lo[0] as f32, lo[1] as f32, lo[2] as f32) / s,
                Vec3::new(hi[0] as f32, hi[1] as f32, hi[2] as f32) / s,
            )
        })
    }
}

/// One posed view's coverage, for carving: a summed-area table of "alpha > 0" so that any
/// rectangle of the image can be tested for coverage in O(1).
#[derive(Debug, Clone)]
pub struct CoverageMask {
    camera: Camera,
    width: u32,
    height: u32,
    /// `(width + 1) x (height + 1)` prefix sums of covered pixels.
    sums: Vec<u32>,
    /// No covered pixel on the image border: the view holds the object's whole silhouette,
    /// so whatever it does not show (outside its frame) is empty.
    complete: bool,
}

impl CoverageMask {
    /// Pixels with alpha above `threshold` count as covered, and so do pixels whose alpha is
    /// NaN: a value nobody knows must not carve matter away.
    pub fn new(camera: Camera, image: &RgbaImage, threshold: f32) -> Self {
        let (w, h) = (image.width(), image.height());
        let is_covered = |alpha: f32| !(alpha <= threshold);
        let stride = w as usize + 1;
        let mut sums = vec![0u32; stride * (h as usize + 1)];
        for y in 0..h as usize {
            let mut row = 0u32;
            for x in 0..w as usize {
                row += u32::from(is_covered(image.pixels()[y * w as usize + x][3]));
                sums[(y + 1) * stride + x + 1] = sums[y * stride + x + 1] + row;
            }
        }
        let covered = |x: u32, y: u32| is_covered(image.pixels()[(y * w + x) as usize][3]);
        let complete =
            !((0..w).any(|x| covered(x, 0) || covered(x, h - 1)) || (0..h).any(|y| covered(0, y) || covered(w - 1, y)));
        CoverageMask { camera, width: w, height: h, sums, complete }
    }

    /// Whether the view shows the whole silhouette (nothing covered on its border).
    pub fn is_complete(&self) -> bool {
        self.complete
    }

    /// Covered pixels in `[x0, x1) x [y0, y1)` (clipped by the caller).
    fn covered(&self, x0: usize, y0: usize, x1: usize, y1: usize) -> u32 {
        let s = self.width as usize + 1;
        self.sums[y1 * s + x1] + self.sums[y0 * s + x0] - self.sums[y0 * s + x1] - self.sums[y1 * s + x0]
    }

    /// What this view says of a sphere (`center`, `radius`): [`Seen::Empty`] if it lies in
    /// front of the camera with its footprint entirely inside the image and no pixel there
    /// covered, or if it is out of the frame of a complete view (one whose border is
    /// transparent: the whole object is inside its frame); [`Seen::Unknown`] if it is out of
    /// the frame of an incomplete view.
    pub fn classify(&self, center: Vec3, radius: f32) -> Seen {
        let out_of_frame = if self.complete { Seen::Empty } else { Seen::Unknown };
        let depth = self.camera.view_depth(center);
        let Some(pixel) = self.camera.project(center) else {
            return out_of_frame;
        };
        if !(pixel.x >= 0.0 && pixel.y >= 0.0 && pixel.x <= self.width as f32 && pixel.y <= self.height as f32) {
            return out_of_frame;
        }
        if depth - radius <= 1e-3 || depth.is_nan() {
            return Seen::Maybe;
        }
        let (fx, fy, _, _) = self.camera.intrinsics();
        // Conservative footprint of the sphere: radius / (depth - radius) in focal units,
        // plus one pixel for the box filter of downscaled masks.
        let spread = radius / (depth - radius);
        let (rx, ry) = (fx * spread * 1.05 + 1.0, fy * spread * 1.05 + 1.0);
        let (x0, x1, y0, y1) =
            ((pixel.x - rx).floor(), (pixel.x + rx).ceil(), (pixel.y - ry).floor(), (pixel.y + ry).ceil());
        if !(x0 >= 0.0 && y0 >= 0.0 && x1 <= self.width as f32 && y1 <= self.height as f32) {
            return Seen::Maybe;
        }
        if self.covered(x0 as usize, y0 as usize, x1 as usize, y1 as usize) == 0 { Seen::Empty } else { Seen::Maybe }
    }
}

/// What one view says about a region of space.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Seen {
    /// Fully visible and transparent: nothing there.
    Empty,
    /// In view, possibly holding matter.
    Maybe,
    /// Outside the view.
    Unknown,
}

/// The visual hull of `masks` over the box `[min, min + size]` at `resolution`: a cell is
/// kept if at least one view has it in its image and no view proves its bounding sphere
/// empty (see [`CoverageMask::classify`]). Cells no view sees are dropped: no training ray can constrain them, and left
/// occupied they would render as fog from new viewpoints. Runs on the rayon pool.
pub fn visual_hull(min: Vec3, size: Vec3, resolution: u32, masks: &[CoverageMask]) -> Option<OccupancyGrid> {
    use rayon::prelude::*;
    if !OccupancyGrid::valid_resolution(resolution) {
        return None;
    }
    let r = resolution as usize;
    let cell = size / resolution as f32;
    let radius = 0.5 * cell.length();
    let flags: Vec<bool> = (0..r * r * r)
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| {
            let (x, y, z) = (i % r, (i / r) % r, i / (r * r));
            let center = min + (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * cell;
            let mut seen = false;
            for m in masks {
                match m.classify(center, radius) {
                    Seen::Empty => return false,
                    Seen::Maybe => seen = true,
                    Seen::Unknown => {}
                }
            }
            seen
        })
        .collect();
    OccupancyGrid::from_flags(resolution, &flags)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;

    #[test]
    fn bits_coarse_blocks_and_bounds() {
        let mut g = OccupancyGrid::filled(16, false);
        assert_eq!(g.occupied_count(), 0);
        assert!(g.occupied_bounds().is_none());
        let i = g.index(9, 3, 15);
        g.set(i, true);
        g.rebuild_coarse();
        assert!(g.get(i) && !g.get(i - 1));
        assert!(g.block_occupied(8, 0, 8) && !g.block_occupied(0, 0, 0));
        let (lo, hi) = g.occupied_bounds().expect("bounds");
        assert_eq!(lo * 16.0, Vec3::new(9.0, 3.0, 15.0));
        assert_eq!(hi * 16.0, Vec3::new(10.0, 4.0, 16.0));
        assert_eq!(OccupancyGrid::filled(24, true).occupied_count(), 24 * 24 * 24);
        let round = OccupancyGrid::from_words(16, g.words().to_vec()).expect("words");
        assert_eq!(round, g);
        assert!(OccupancyGrid::from_words(16, vec![0; 3]).is_none());
        assert!(!OccupancyGrid::valid_resolution(20) && !OccupancyGrid::valid_resolution(8));
    }

    #[test]
    fn visual_hull_of_a_disc_seen_from_above_keeps_a_column() {
        // A camera straight above the unit cube sees a covered disc in the middle of its
        // image: cells above and below the disc's footprint survive, cells outside it go.
        let eye = Vec3::new(0.5, 0.5, 5.0);
        let c2w = Mat4::from_translation(eye);
        let camera = Camera::from_fov_x(64, 64, 0.5, c2w).expect("camera");
        let image = RgbaImage::from_fn(64, 64, |x, y| {
            let (dx, dy) = (x as f32 + 0.5 - 32.0, y as f32 + 0.5 - 32.0);
            [1.0, 1.0, 1.0, if dx * dx + dy * dy < 36.0 { 1.0 } else { 0.0 }]
        });
        let mask = CoverageMask::new(camera, &image, 0.0);
        let hull = visual_hull(Vec3::ZERO, Vec3::ONE, 16, &[mask]).expect("hull");
        let centre = hull.index(8, 8, 2);
        let corner = hull.index(0, 0, 8);
        assert!(hull.get(centre) && !hull.get(corner));
        assert!(hull.occupied_count() < hull.cell_count() * 2 / 5, "{}", hull.occupied_count());
    }
}
