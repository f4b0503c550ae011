//! A bounding volume hierarchy over triangles: binned SAH build, flattened depth-first
//! layout (left child follows its parent), then collapsed into a 4-wide tree whose four child
//! boxes are tested by one SIMD slab test (SSE through glam's `Vec4`); traversal visits the
//! children hit nearest first and drops a pushed child the ray reaches only beyond a hit found
//! meanwhile. The binary tree stays: its traversal is the fallback for trees too deep for the
//! wide traversal's stack (degenerate meshes).

use glam::{Vec3, Vec4};

use nephele_geometry::camera::Ray;

use super::scene::Mesh;

const MAX_LEAF_TRIANGLES: usize = 4;
const SAH_BINS: usize = 16;
/// Relative cost of a node visit against a ray-triangle test in the SAH.
const TRAVERSAL_COST: f32 = 1.0;
const STACK_SIZE: usize = 64;

/// Axis-aligned box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb { min: Vec3::splat(f32::INFINITY), max: Vec3::splat(f32::NEG_INFINITY) };

    pub fn grow(&mut self, p: Vec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }

    pub fn union(&self, other: &Aabb) -> Aabb {
        Aabb { min: self.min.min(other.min), max: self.max.max(other.max) }
    }

    pub fn surface_area(&self) -> f32 {
        let d = (self.max - self.min).max(Vec3::ZERO);
        2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
    }

    /// Slab test; returns the entry distance when the ray overlaps `[t_min, t_max]`.
    /// `inv_dir` may hold infinities (axis-parallel rays); `max`/`min` drop the NaN that
    /// `0 * inf` gives for an origin exactly on a slab plane, keeping the test conservative.
    #[inline]
    fn hit(&self, origin: Vec3, inv_dir: Vec3, t_min: f32, t_max: f32) -> Option<f32> {
        let t0 = (self.min - origin) * inv_dir;
        let t1 = (self.max - origin) * inv_dir;
        let near = t0.min(t1);
        let far = t0.max(t1);
        let enter = near.x.max(near.y).max(near.z).max(t_min);
        let exit = far.x.min(far.y).min(far.z).min(t_max);
        (enter <= exit).then_some(enter)
    }
}

/// Flattened node: an inner node's left child is the next node, `offset` is the right child;
/// a leaf's `offset` is its first triangle and `count` its triangle count (> 0).
#[derive(Debug, Clone, Copy)]
struct Node {
    bounds: Aabb,
    offset: u32,
    count: u32,
    /// Split axis of an inner node, to visit the nearer child first.
    axis: u8,
}

/// A triangle as the intersector wants it: one vertex and two edges.
#[derive(Debug, Clone, Copy)]
struct PackedTriangle {
    v0: Vec3,
    e1: Vec3,
    e2: Vec3,
}

/// The closest hit along a ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction.
    pub t: f32,
    /// Index of the triangle in the mesh the BVH was built from.
    pub triangle: u32,
    /// Barycentric coordinates of the hit: weight of vertex 1 and vertex 2.
    pub u: f32,
    pub v: f32,
}

/// Work counters, summed by the caller over many rays.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TraversalStats {
    pub rays: u64,
    /// Nodes of the 4-wide tree visited (four box tests each; binary nodes on the fallback).
    pub node_visits: u64,
    pub triangle_tests: u64,
}

impl std::ops::AddAssign for TraversalStats {
    fn add_assign(&mut self, o: Self) {
        self.rays += o.rays;
        self.node_visits += o.node_visits;
        self.triangle_tests += o.triangle_tests;
    }
}

/// Four child boxes side by side (structure of arrays, one `Vec4` per bound and axis).
#[derive(Debug, Clone, Copy)]
struct WideNode {
    /// Box minima of the four slots, x then y then z.
    min: [Vec4; 3],
    max: [Vec4; 3],
    /// Per slot: the child's wide node (inner child) or its first triangle (leaf).
    child: [u32; 4],
    /// Per slot: a leaf's triangle count, 0 for an inner child, [`EMPTY_SLOT`] for none.
    count: [u32; 4],
}

/// Count of a slot that holds no child.
const EMPTY_SLOT: u32 = u32::MAX;

/// Entries of the wide traversal's stack; a deeper tree falls back to the binary traversal.
const WIDE_STACK_SIZE: usize = 128;

impl WideNode {
    const EMPTY: WideNode =
        WideNode { min: [Vec4::ZERO; 3], max: [Vec4::ZERO; 3], child: [0; 4], count: [EMPTY_SLOT; 4] };

    fn set_slot(&mut self, lane: usize, bounds: &Aabb, child: u32, count: u32) {
        for a in 0..3 {
            self.min[a][lane] = bounds.min[a];
            self.max[a][lane] = bounds.max[a];
        }
        self.child[lane] = child;
        self.count[lane] = count;
    }
}

#[derive(Debug, Clone)]
pub struct Bvh {
    /// The 4-wide tree that rays traverse (root at 0; empty when `nodes` is).
    wide: Vec<WideNode>,
    nodes: Vec<Node>,
    triangles: Vec<PackedTriangle>,
    /// Original mesh index of each packed triangle.
    triangle_ids: Vec<u32>,
}

struct BuildItem {
    bounds: Aabb,
    centroid: Vec3,
    id: u32,
}

impl Bvh {
    /// Builds over every triangle of `mesh` (indices assumed validated).
    pub fn build(mesh: &Mesh) -> Bvh {
        let mut items: Vec<BuildItem> = mesh
            .indices
            .iter()
            .enumerate()
            .map(|(id, tri)| {
                let mut bounds = Aabb::EMPTY;
                for &i in tri {
                    bounds.grow(mesh.positions[i as usize]);
                }
                BuildItem { bounds, centroid: (bounds.min + bounds.max) * 0.5, id: id as u32 }
            })
            .collect();
        let mut nodes = Vec::with_capacity(items.len().max(1) * 2);
        if !items.is_empty() {
            let len = items.len();
            build_recursive(&mut items, 0, len, &mut nodes);
        }
        let triangle_ids: Vec<u32> = items.iter().map(|it| it.id).collect();
        let triangles = triangle_ids
            .iter()
            .map(|&id| {
                let [a, b, c] = mesh.indices[id as usize].map(|i| mesh.positions[i as usize]);
                PackedTriangle { v0: a, e1: b - a, e2: c - a }
            })
            .collect();
        let mut wide = Vec::with_capacity(nodes.len() / 2 + 1);
        if !nodes.is_empty() {
            collapse(&nodes, 0, &mut wide);
        }
        Bvh { wide, nodes, triangles, triangle_ids }
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    pub fn bounds(&self) -> Option<Aabb> {
        self.nodes.first().map(|n| n.bounds)
    }

    /// Closest hit with `t` in `(t_min, t_max)`.
    pub fn intersect(&self, ray: &Ray, t_min: f32, t_max: f32, stats: &mut TraversalStats) -> Option<Hit> {
        self.traverse_wide(ray, t_min, t_max, false, stats)
    }

    /// Whether anything blocks the ray in `(t_min, t_max)` (shadow rays: first hit wins).
    pub fn occluded(&self, ray: &Ray, t_min: f32, t_max: f32, stats: &mut TraversalStats) -> bool {
        self.traverse_wide(ray, t_min, t_max, true, stats).is_some()
    }

    /// The 4-wide traversal (`node_visits` counts wide nodes: four box tests each). Stack
    /// entries are `(child, count, entry distance)`: leaves are tested when popped, so the
    /// nearest hit child of a node, leaf or not, is always handled first.
    fn traverse_wide(
        &self,
        ray: &Ray,
        t_min: f32,
        mut t_max: f32,
        any_hit: bool,
        stats: &mut TraversalStats,
    ) -> Option<Hit> {
        if self.wide.is_empty() || !ray.origin.is_finite() || !ray.direction.is_finite() {
            stats.rays += 1;
            return None;
        }
        let inv_dir = ray.direction.recip();
        let origin = [Vec4::splat(ray.origin.x), Vec4::splat(ray.origin.y), Vec4::splat(ray.origin.z)];
        let inv = [Vec4::splat(inv_dir.x), Vec4::splat(inv_dir.y), Vec4::splat(inv_dir.z)];
        let mut best: Option<Hit> = None;
        let mut stack = [(0u32, 0u32, 0f32); WIDE_STACK_SIZE];
        stack[0] = (0, 0, t_min);
        let mut top = 1usize;
        while top > 0 {
            top -= 1;
            let (child, count, enter) = stack[top];
            if enter > t_max {
                continue;
            }
            if count > 0 {
                if self.intersect_leaf(child, count, ray, t_min, &mut t_max, any_hit, &mut best, stats) {
                    stats.rays += 1;
                    return best;
                }
                continue;
            }
            let node = &self.wide[child as usize];
            stats.node_visits += 1;
            // Slab test of the four boxes. A NaN (0 * inf: an origin on a slab plane of a box
            // the axis-parallel ray runs along) drops that axis' bound: conservative.
            let (mut near, mut far) = (Vec4::splat(t_min), Vec4::splat(t_max));
            for a in 0..3 {
                let t0 = (node.min[a] - origin[a]) * inv[a];
                let t1 = (node.max[a] - origin[a]) * inv[a];
                let lo = t0.min(t1);
                let hi = t0.max(t1);
                near = near.max(Vec4::select(lo.is_nan_mask(), Vec4::NEG_INFINITY, lo));
                far = far.min(Vec4::select(hi.is_nan_mask(), Vec4::INFINITY, hi));
            }
            let mask = near.cmple(far).bitmask();
            // The hit slots, nearest first (insertion sort of at most four).
            let mut hits = [(0f32, 0usize); 4];
            let mut n = 0;
            for lane in 0..4 {
                if mask & (1 << lane) != 0 && node.count[lane] != EMPTY_SLOT {
                    let mut j = n;
                    while j > 0 && hits[j - 1].0 > near[lane] {
                        hits[j] = hits[j - 1];
                        j -= 1;
                    }
                    hits[j] = (near[lane], lane);
                    n += 1;
                }
            }
            if top + n > WIDE_STACK_SIZE {
                // Deeper than any sane tree: the binary traversal (which counts the ray)
                // finishes the search below the best hit so far.
                return self.traverse(ray, t_min, t_max, any_hit, stats).or(best);
            }
            // Farthest pushed first, so the nearest is popped next.
            for &(enter, lane) in hits[..n].iter().rev() {
                stack[top] = (node.child[lane], node.count[lane], enter);
                top += 1;
            }
        }
        stats.rays += 1;
        best
    }

    fn traverse(
        &self,
        ray: &Ray,
        t_min: f32,
        mut t_max: f32,
        any_hit: bool,
        stats: &mut TraversalStats,
    ) -> Option<Hit> {
        stats.rays += 1;
        if self.nodes.is_empty() || !ray.origin.is_finite() || !ray.direction.is_finite() {
            return None;
        }
        let origin = ray.origin;
        let inv_dir = ray.direction.recip();
        let negative = [inv_dir.x < 0.0, inv_dir.y < 0.0, inv_dir.z < 0.0];
        let mut best: Option<Hit> = None;
        let mut stack = [0u32; STACK_SIZE];
        let mut top = 0usize;
        let mut index = 0usize;
        loop {
            let node = &self.nodes[index];
            stats.node_visits += 1;
            if node.bounds.hit(origin, inv_dir, t_min, t_max).is_some() {
                if node.count > 0 {
                    if self.intersect_leaf(node.offset, node.count, ray, t_min, &mut t_max, any_hit, &mut best, stats) {
                        return best;
                    }
                } else {
                    // Visit the child on the ray's near side first; push the other.
                    let (near, far) = if negative[node.axis as usize] {
                        (node.offset as usize, index + 1)
                    } else {
                        (index + 1, node.offset as usize)
                    };
                    if top < STACK_SIZE {
                        stack[top] = far as u32;
                        top += 1;
                    } else {
                        // Depth beyond the stack cannot happen with SAH on sane input, but a
                        // degenerate mesh must not crash the renderer: fall back to recursion.
                        if let Some(h) = self.traverse_from(far, ray, t_min, t_max, any_hit, stats) {
                            t_max = h.t;
                            best = Some(h);
                            if any_hit {
                                return best;
                            }
                        }
                    }
                    index = near;
                    continue;
                }
            }
            if top == 0 {
                break;
            }
            top -= 1;
            index = stack[top] as usize;
        }
        best
    }

    /// Tests the leaf's triangles `first..first + count` in `(t_min, *t_max)`: each hit lowers
    /// `*t_max` and becomes `*best`. Returns whether the search is over (a hit, when any hit
    /// will do).
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn intersect_leaf(
        &self,
        first: u32,
        count: u32,
        ray: &Ray,
        t_min: f32,
        t_max: &mut f32,
        any_hit: bool,
        best: &mut Option<Hit>,
        stats: &mut TraversalStats,
    ) -> bool {
        let first = first as usize;
        for k in first..first + count as usize {
            stats.triangle_tests += 1;
            if let Some((t, u, v)) = intersect_triangle(&self.triangles[k], ray.origin, ray.direction, t_min, *t_max) {
                *t_max = t;
                *best = Some(Hit { t, triangle: self.triangle_ids[k], u, v });
                if any_hit {
                    return true;
                }
            }
        }
        false
    }

    /// Brute-force subtree walk, used only if the explicit stack overflows.
    fn traverse_from(
        &self,
        index: usize,
        ray: &Ray,
        t_min: f32,
        t_max: f32,
        any_hit: bool,
        stats: &mut TraversalStats,
    ) -> Option<Hit> {
        let node = &self.nodes[index];
        stats.node_visits += 1;
        node.bounds.hit(ray.origin, ray.direction.recip(), t_min, t_max)?;
        if node.count > 0 {
            let mut best: Option<Hit> = None;
            let mut t_max = t_max;
            self.intersect_leaf(node.offset, node.count, ray, t_min, &mut t_max, any_hit, &mut best, stats);
            return best;
        }
        let left = self.traverse_from(index + 1, ray, t_min, t_max, any_hit, stats);
        if any_hit && left.is_some() {
            return left;
        }
        let limit = left.map_or(t_max, |h| h.t);
        self.traverse_from(node.offset as usize, ray, t_min, limit, any_hit, stats).or(left)
    }
}

/// The wide node of binary inner node `index` (or of a root leaf): its two children, then
/// repeatedly the inner slot of largest surface area opened into its two children, until four
/// slots or only leaves. Returns the wide node's index.
fn collapse(nodes: &[Node], index: usize, wide: &mut Vec<WideNode>) -> u32 {
    let mut slots: Vec<usize> =
        if nodes[index].count > 0 { vec![index] } else { vec![index + 1, nodes[index].offset as usize] };
    while slots.len() < 4 {
        let widest = slots
            .iter()
            .enumerate()
            .filter(|(_, s)| nodes[**s].count == 0)
            .max_by(|a, b| nodes[*a.1].bounds.surface_area().total_cmp(&nodes[*b.1].bounds.surface_area()));
        let Some((k, &s)) = widest else { break };
        slots.swap_remove(k);
        slots.push(s + 1);
        slots.push(nodes[s].offset as usize);
    }
    let me = wide.len();
    wide.push(WideNode::EMPTY);
    for (lane, &s) in slots.iter().enumerate() {
        let node = &nodes[s];
        let (child, count) = if node.count > 0 { (node.offset, node.count) } else { (collapse(nodes, s, wide), 0) };
        wide[me].set_slot(lane, &node.bounds, child, count);
    }
    me as u32
}

/// Möller-Trumbore. Double-sided; returns `(t, u, v)`.
#[inline]
fn intersect_triangle(
    tri: &PackedTriangle,
    origin: Vec3,
    dir: Vec3,
    t_min: f32,
    t_max: f32,
) -> Option<(f32, f32, f32)> {
    let p = dir.cross(tri.e2);
    let det = tri.e1.dot(p);
    if det.abs() < 1e-12 {
        return None;
    }
    let inv_det = 1.0 / det;
    let s = origin - tri.v0;
    let u = s.dot(p) * inv_det;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(tri.e1);
    let v = dir.dot(q) * inv_det;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = tri.e2.dot(q) * inv_det;
    (t > t_min && t < t_max).then_some((t, u, v))
}

fn build_recursive(items: &mut [BuildItem], start: usize, end: usize, nodes: &mut Vec<Node>) -> usize {
    let slice = &mut items[start..end];
    let mut bounds = Aabb::EMPTY;
    let mut centroid_bounds = Aabb::EMPTY;
    for it in slice.iter() {
        bounds = bounds.union(&it.bounds);
        centroid_bounds.grow(it.centroid);
    }
    let index = nodes.len();
    nodes.push(Node { bounds, offset: start as u32, count: (end - start) as u32, axis: 0 });
    let count = end - start;
    if count <= MAX_LEAF_TRIANGLES {
        return index;
    }
    let extent = centroid_bounds.max - centroid_bounds.min;
    let axis = if extent.x >= extent.y && extent.x >= extent.z {
        0
    } else if extent.y >= extent.z {
        1
    } else {
        2
    };
    let lo = centroid_bounds.min[axis];
    let span = extent[axis];
    let split = if span <= 0.0 || !span.is_finite() {
        None // all centroids coincide: any order is as good as another
    } else {
        match best_sah_split(slice, axis, lo, span, &bounds) {
            Some(bin) => {
                let scale = SAH_BINS as f32 / span;
                let n = partition(slice, |it| bin_of(it.centroid[axis], lo, scale) <= bin);
                (n > 0 && n < count).then_some(n)
            }
            None => return index, // a leaf is cheaper than any split
        }
    };
    let mid = start
        + split.unwrap_or_else(|| {
            // Median split along the axis when binning could not separate the triangles.
            slice.select_nth_unstable_by(count / 2, |a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
            count / 2
        });
    nodes[index].count = 0;
    nodes[index].axis = axis as u8;
    build_recursive(items, start, mid, nodes);
    let right = build_recursive(items, mid, end, nodes);
    nodes[index].offset = right as u32;
    index
}

fn bin_of(c: f32, lo: f32, scale: f32) -> usize {
    (((c - lo) * scale) as usize).min(SAH_BINS - 1)
}

/// Returns the last bin of the left side for the cheapest split, or `None` if no split beats
/// a leaf of `slice.len()` triangles (only considered when the leaf is small enough).
fn best_sah_split(slice: &[BuildItem], axis: usize, lo: f32, span: f32, bounds: &Aabb) -> Option<usize> {
    let scale = SAH_BINS as f32 / span;
    let mut bin_bounds = [Aabb::EMPTY; SAH_BINS];
    let mut bin_counts = [0usize; SAH_BINS];
    for it in slice {
        let b = bin_of(it.centroid[axis], lo, scale);
        bin_bounds[b] = bin_bounds[b].union(&it.bounds);
        bin_counts[b] += 1;
    }
    // Sweep from the right to get the right-hand areas and counts for each split.
    let mut right_area = [0.0f32; SAH_BINS];
    let mut right_count = [0usize; SAH_BINS];
    let mut acc = Aabb::EMPTY;
    let mut n = 0;
    for b in (1..SAH_BINS).rev() {
        acc = acc.union(&bin_bounds[b]);
        n += bin_counts[b];
        right_area[b] = acc.surface_area();
        right_count[b] = n;
    }
    let mut best = None;
    let mut best_cost = f32::INFINITY;
    let mut left = Aabb::EMPTY;
    let mut left_n = 0;
    for b in 0..SAH_BINS - 1 {
        left = left.union(&bin_bounds[b]);
        left_n += bin_counts[b];
        if left_n == 0 || right_count[b + 1] == 0 {
            continue;
        }
        let cost = left.surface_area() * left_n as f32 + right_area[b + 1] * right_count[b + 1] as f32;
        if cost < best_cost {
            best_cost = cost;
            best = Some(b);
        }
    }
    let parent_area = bounds.surface_area().max(f32::MIN_POSITIVE);
    let split_cost = TRAVERSAL_COST + best_cost / parent_area;
    let leaf_cost = slice.len() as f32;
    if slice.len() <= 2 * MAX_LEAF_TRIANGLES && leaf_cost <= split_cost && best.is_some() {
        return None;
    }
    best
}

/// In-place partition; returns the number of items for which `pred` holds (moved to the front).
fn partition(slice: &mut [BuildItem], pred: impl Fn(&BuildItem) -> bool) -> usize {
    let mut i = 0;
    for j in 0..slice.len() {
        if pred(&slice[j]) {
            slice.swap(i, j);
            i += 1;
        }
    }
    i
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::{Rng, uniform_sphere};

    fn random_soup(n: usize, seed: u64) -> Mesh {
        let mut rng = Rng::new(seed, 0);
        let mut positions = Vec::new();
        let mut indices = Vec::new();
        for k in 0..n {
            let c = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 10.0 - 5.0;
            for _ in 0..3 {
                positions.push(c + Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5);
            }
            let b = 3 * k as u32;
            indices.push([b, b + 1, b + 2]);
        }
        Mesh::new(positions, indices)
    }

    fn brute_force(mesh: &Mesh, ray: &Ray) -> Option<(f32, u32)> {
        let mut best: Option<(f32, u32)> = None;
        for (id, tri) in mesh.indices.iter().enumerate() {
            let [a, b, c] = tri.map(|i| mesh.positions[i as usize]);
            let packed = PackedTriangle { v0: a, e1: b - a, e2: c - a };
            let limit = best.map_or(f32::INFINITY, |b| b.0);
            if let Some((t, _, _)) = intersect_triangle(&packed, ray.origin, ray.direction, 0.0, limit) {
                best = Some((t, id as u32));
            }
        }
        best
    }

    #[test]
    fn bvh_agrees_with_brute_force_including_axis_parallel_rays() {
        let mesh = random_soup(2000, 3);
        let bvh = Bvh::build(&mesh);
        let mut rng = Rng::new(9, 9);
        let mut stats = TraversalStats::default();
        let axis_dirs = [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z];
        for k in 0..3000 {
            let origin = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 14.0 - 7.0;
            let direction = if k % 5 == 0 { axis_dirs[k % 6] } else { uniform_sphere(rng.next_vec2()) };
            let ray = Ray { origin, direction };
            let expected = brute_force(&mesh, &ray);
            let got = bvh.intersect(&ray, 0.0, f32::INFINITY, &mut stats);
            match (expected, got) {
                (None, None) => {}
                (Some((t, _)), Some(h)) => assert!((t - h.t).abs() < 1e-4, "t {t} vs {}", h.t),
                (e, g) => panic!("ray {ray:?}: brute force {e:?}, bvh {g:?}"),
            }
            assert_eq!(bvh.occluded(&ray, 0.0, f32::INFINITY, &mut stats), expected.is_some());
        }
        // The BVH must do far less work than testing all 2000 triangles.
        assert!(stats.triangle_tests / stats.rays < 200, "{stats:?}");
    }

    /// Axis-aligned unit boxes on a lattice: many box faces share planes with the rays below.
    fn lattice_of_boxes() -> Mesh {
        let mut positions = Vec::new();
        let mut indices = Vec::new();
        for (x, y, z) in (0..4).flat_map(|x| (0..4).flat_map(move |y| (0..3).map(move |z| (x, y, z)))) {
            let lo = Vec3::new(x as f32, y as f32, z as f32) * 2.0;
            let b = positions.len() as u32;
            for k in 0..8 {
                positions.push(lo + Vec3::new((k & 1) as f32, ((k >> 1) & 1) as f32, (k >> 2) as f32));
            }
            for [p, q, r, s] in [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]] {
                indices.push([b + p, b + q, b + r]);
                indices.push([b + p, b + r, b + s]);
            }
        }
        Mesh::new(positions, indices)
    }

    #[test]
    fn wide_and_binary_traversals_agree_on_rays_along_box_faces() {
        let mesh = lattice_of_boxes();
        let bvh = Bvh::build(&mesh);
        assert!(bvh.wide.len() < bvh.nodes.len());
        let mut rng = Rng::new(5, 1);
        let mut stats = TraversalStats::default();
        let axis_dirs = [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z];
        let mut hits = 0;
        for k in 0..4000 {
            // Origins on the lattice's planes (integer coordinates) half of the time.
            let mut origin = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 9.0 - 1.0;
            if k % 2 == 0 {
                origin = origin.round();
            }
            let direction = if k % 3 == 0 { axis_dirs[k % 6] } else { uniform_sphere(rng.next_vec2()) };
            let ray = Ray { origin, direction };
            for t_max in [f32::INFINITY, 3.0] {
                let wide = bvh.intersect(&ray, 1e-4, t_max, &mut stats);
                let binary = bvh.traverse(&ray, 1e-4, t_max, false, &mut stats);
                match (wide, binary) {
                    (None, None) => {}
                    (Some(w), Some(b)) => {
                        assert!((w.t - b.t).abs() <= 1e-6 * (1.0 + b.t), "ray {ray:?}: wide {w:?}, binary {b:?}");
                        hits += 1;
                    }
                    (w, b) => panic!("ray {ray:?} to {t_max}: wide {w:?}, binary {b:?}"),
                }
                assert_eq!(bvh.occluded(&ray, 1e-4, t_max, &mut stats), binary.is_some(), "ray {ray:?}");
            }
        }
        assert!(hits > 1000, "{hits} hits");
    }

    #[test]
    fn degenerate_inputs_do_not_crash() {
        // Many identical triangles (centroids coincide) and a NaN ray.
        let mesh = Mesh::new(vec![Vec3::ZERO, Vec3::X, Vec3::Y], vec![[0, 1, 2]; 1000]);
        let bvh = Bvh::build(&mesh);
        let mut stats = TraversalStats::default();
        let ray = Ray { origin: Vec3::new(0.2, 0.2, 1.0), direction: -Vec3::Z };
        let hit = bvh.intersect(&ray, 0.0, f32::INFINITY, &mut stats).expect("hit");
        assert!((hit.t - 1.0).abs() < 1e-6);
        let nan = Ray { origin: Vec3::NAN, direction: Vec3::Z };
        assert!(bvh.intersect(&nan, 0.0, f32::INFINITY, &mut stats).is_none());
        let empty = Bvh::build(&Mesh::default());
        assert!(empty.intersect(&ray, 0.0, f32::INFINITY, &mut stats).is_none());
    }
}
