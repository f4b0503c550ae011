//! Perfect Spatial Hashing (Lefebvre and Hoppe, SIGGRAPH 2006).
//!
//! A sparse set of `n` occupied voxels of a `u^3` grid is packed into a dense hash table `H`
//! of `m^3 >= n` slots with no collision at all, through a small offset table `Φ` of `r^3`
//! entries (paper section 3):
//!
//! ```text
//! h(p) = (h0(p) + Φ[h1(p)]) mod m,   h0(p) = p mod m,   h1(p) = p mod r
//! ```
//!
//! All points with the same `h1` form a *bucket*; one offset moves the whole bucket. With
//! `gcd(m, r) = 1` and `m r >= u`, the points of one bucket have distinct `h0` (a clash would
//! need `p ≡ p' (mod m r)` on every axis), so only clashes *between* buckets remain, and the
//! construction removes them by choosing `Φ` bucket by bucket, largest first (section 4.2).
//! The table is single-resolution and a query is two table reads plus a key check, which is
//! why NEPHELE (section 4, table 1) prefers it to a multiresolution hash grid on the cache.
//!
//! Coherence (paper section 4.3): if neighbouring entries `q` and `q + e` of `Φ` hold the same
//! offset, the voxels `p` and `p + e` of the two buckets land in neighbouring slots
//! `h(p) + e`. The construction therefore first tries the offsets already given to the
//! neighbours of `q` in `Φ`, and only then searches the free slots.
//!
//! Each slot stores its voxel's key, so a query for an unoccupied voxel is rejected instead
//! of aliasing onto some occupied voxel's data.

use nephele_geometry::SplitMix64;
use thiserror::Error;

/// Largest grid side the keys can hold (10 bits per axis).
pub const MAX_DOMAIN: u32 = 1024;
/// Largest hash or offset table side accepted (so `side^3` fits comfortably in memory).
pub const MAX_TABLE_SIDE: u32 = 1024;
/// Key of an empty slot.
pub const EMPTY_KEY: u32 = u32::MAX;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum PshError {
    #[error("grid side {0} is outside 1..={MAX_DOMAIN}")]
    BadDomain(u32),
    #[error("voxel ({x}, {y}, {z}) lies outside the {u}^3 grid")]
    PointOutside { x: u32, y: u32, z: u32, u: u32 },
    #[error("bad option: {0}")]
    BadOption(&'static str),
    #[error("no perfect hash found for {n} points after {attempts} attempts (last r = {r}, m = {m})")]
    NoPerfectHash { n: usize, attempts: u32, r: u32, m: u32 },
    #[error("table side {0} exceeds {MAX_TABLE_SIDE}")]
    TooLarge(u32),
}

/// Construction parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PshOptions {
    /// Hash table slots per point: `m = ceil((n * table_factor)^(1/3))` (>= 1).
    pub table_factor: f32,
    /// Initial offset table size relative to `n`: `r = ceil((sigma * n)^(1/3))`. The paper
    /// starts at `sigma = 1 / (2 d) = 1/6` in 3D (section 4.2).
    pub sigma: f32,
    /// How many times `r` may grow (by 5 %, at least by one) after a failed attempt.
    pub max_attempts: u32,
    /// Seed of the start positions of the free-slot search (deterministic builds).
    pub seed: u64,
    /// Try the offsets of already-assigned neighbours in `Φ` first (section 4.3).
    pub coherence: bool,
    /// Order buckets by size class (`floor(log2(size))`) rather than exact size, scan order
    /// inside a class, so that neighbouring buckets are assigned one after another while the
    /// table is still empty enough for them to share offsets.
    pub coarse_order: bool,
}

impl PshOptions {
    /// The settings i-NOLF uses: a larger offset table (`sigma = 1`, so buckets hold about one
    /// voxel and neighbouring entries can share offsets) and a half-empty hash table margin
    /// (`table_factor = 1.5`). On surface occupancies this raises the share of neighbouring
    /// voxels in neighbouring slots from ~7 % (the paper's defaults) to ~40 % for 6 more bytes
    /// per voxel (see inolf-BENCH).
    pub fn coherent() -> PshOptions {
        PshOptions { table_factor: 1.5, sigma: 1.0, coarse_order: true, ..PshOptions::default() }
    }
}

impl Default for PshOptions {
    fn default() -> Self {
        PshOptions {
            table_factor: 1.05,
            sigma: 1.0 / 6.0,
            max_attempts: 64,
            seed: 0x5eed,
            coherence: true,
            coarse_order: false,
        }
    }
}

/// What a build did, for reports.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PshBuildStats {
    /// Attempts (offset-table sizes tried) until one succeeded.
    pub attempts: u32,
    /// Buckets whose offset was copied from a neighbouring `Φ` entry.
    pub coherent_buckets: u64,
    /// Buckets whose offset came from the free-slot search.
    pub searched_buckets: u64,
    /// Largest bucket.
    pub max_bucket: u32,
}

/// A perfect spatial hash of a set of voxels: query by voxel, get a unique slot in `0..m^3`.
#[derive(Debug, Clone, PartialEq)]
pub struct PshTable {
    u: u32,
    m: u32,
    r: u32,
    n: usize,
    /// `Φ`, `r^3` entries, each coordinate `< m`; index `x + r (y + r z)`.
    offsets: Vec<[u16; 3]>,
    /// `m^3` slots, each the packed key of its voxel or [`EMPTY_KEY`]; index `x + m (y + m z)`.
    keys: Vec<u32>,
    /// `c mod r` and `c mod m` for every coordinate `c < u`, so that a query divides nothing
    /// (it took nine integer divisions per voxel, each tens of cycles of latency; `perf` put
    /// only a few per cent of the look-up on them, most of it waited on the tables' reads).
    residues: Residues,
}

/// Where the 8 voxels of a cell would sit in a [`PshTable`] ([`PshTable::probe_cell`]): the
/// slots they hash to (always inside the table), their packed keys, and a bit per voxel
/// inside the grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellProbe {
    pub(crate) slots: [u32; 8],
    keys: [u32; 8],
    inside: u8,
}

/// Residues of the grid coordinates, derived from `u`, `m` and `r`.
#[derive(Debug, Clone, PartialEq)]
struct Residues {
    mod_r: Vec<u16>,
    mod_m: Vec<u16>,
}

impl Residues {
    fn new(u: u32, m: u32, r: u32) -> Residues {
        Residues { mod_r: (0..u).map(|c| (c % r) as u16).collect(), mod_m: (0..u).map(|c| (c % m) as u16).collect() }
    }
}

/// Packs a voxel coordinate (each `< 1024`) into a key.
#[inline]
pub fn pack_key(p: [u32; 3]) -> u32 {
    p[0] | (p[1] << 10) | (p[2] << 20)
}

/// Inverse of [`pack_key`].
#[inline]
pub fn unpack_key(k: u32) -> [u32; 3] {
    [k & 1023, (k >> 10) & 1023, (k >> 20) & 1023]
}

fn gcd(mut a: u32, mut b: u32) -> u32 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Smallest `r' >= r` with `gcd(r', m) = 1` and `m r' >= u`.
fn admissible_r(mut r: u32, m: u32, u: u32) -> u32 {
    r = r.max(1).max(u.div_ceil(m.max(1)));
    while gcd(r, m) != 1 {
        r += 1;
    }
    r
}

impl PshTable {
    /// Builds the perfect hash of `points` (voxels of a `u^3` grid; duplicates are ignored).
    pub fn build(u: u32, points: &[[u32; 3]], options: &PshOptions) -> Result<(PshTable, PshBuildStats), PshError> {
        if u == 0 || u > MAX_DOMAIN {
            return Err(PshError::BadDomain(u));
        }
        if !(options.table_factor.is_finite() && options.table_factor >= 1.0) {
            return Err(PshError::BadOption("table_factor must be >= 1"));
        }
        if !(options.sigma.is_finite() && options.sigma > 0.0) {
            return Err(PshError::BadOption("sigma must be > 0"));
        }
        if let Some(p) = points.iter().find(|p| p.iter().any(|&c| c >= u)) {
            return Err(PshError::PointOutside { x: p[0], y: p[1], z: p[2], u });
        }
        let mut keys: Vec<u32> = points.iter().map(|&p| pack_key(p)).collect();
        keys.sort_unstable();
        keys.dedup();
        let n = keys.len();
        let points: Vec<[u32; 3]> = keys.iter().map(|&k| unpack_key(k)).collect();

        let m = ((n.max(1) as f64 * f64::from(options.table_factor)).cbrt().ceil() as u32).max(1);
        if m > MAX_TABLE_SIDE {
            return Err(PshError::TooLarge(m));
        }
        let mut r = admissible_r((f64::from(options.sigma) * n as f64).cbrt().ceil() as u32, m, u);
        let mut stats = PshBuildStats::default();
        let mut rng = SplitMix64::new(options.seed);
        for attempt in 1..=options.max_attempts.max(1) {
            if r > MAX_TABLE_SIDE {
                return Err(PshError::TooLarge(r));
            }
            stats.attempts = attempt;
            if let Some(table) = Self::try_build(u, m, r, &points, options, &mut rng, &mut stats) {
                return Ok((table, stats));
            }
            tracing::debug!(n, m, r, "perfect spatial hash failed, growing the offset table");
            r = admissible_r(r.saturating_add((r / 20).max(1)), m, u);
        }
        Err(PshError::NoPerfectHash { n, attempts: stats.attempts, r, m })
    }

    /// One attempt at a fixed `(m, r)` (paper section 4.2). `None` when some bucket fits
    /// nowhere.
    fn try_build(
        u: u32,
        m: u32,
        r: u32,
        points: &[[u32; 3]],
        options: &PshOptions,
        rng: &mut SplitMix64,
        stats: &mut PshBuildStats,
    ) -> Option<PshTable> {
        let (mu, ru) = (m as usize, r as usize);
        let r3 = ru * ru * ru;
        let m3 = mu * mu * mu;
        let q_of = |p: [u32; 3]| (p[0] % r) as usize + ru * ((p[1] % r) as usize + ru * (p[2] % r) as usize);

        // Buckets by counting sort over Φ entries.
        let mut start = vec![0u32; r3 + 1];
        for &p in points {
            start[q_of(p) + 1] += 1;
        }
        for q in 0..r3 {
            start[q + 1] += start[q];
        }
        let mut fill = start.clone();
        let mut bucketed = vec![[0u32; 3]; points.len()];
        for &p in points {
            let q = q_of(p);
            bucketed[fill[q] as usize] = p;
            fill[q] += 1;
        }
        // Largest buckets first; equal sizes in scan order, so that neighbouring Φ entries
        // are assigned one after another and can share offsets (coherence).
        let mut order: Vec<u32> = (0..r3 as u32).filter(|&q| start[q as usize + 1] > start[q as usize]).collect();
        let coarse = options.coarse_order;
        order.sort_by_key(|&q| {
            let size = start[q as usize + 1] - start[q as usize];
            std::cmp::Reverse(if coarse { 32 - size.leading_zeros() } else { size })
        });
        stats.max_bucket = order.first().map_or(0, |&q| start[q as usize + 1] - start[q as usize]);

        let mut offsets = vec![[0u16; 3]; r3];
        let mut assigned = vec![false; r3];
        let mut slots = vec![EMPTY_KEY; m3];
        // Free slots, compacted lazily.
        let mut free: Vec<u32> = (0..m3 as u32).collect();
        let mut used_since_compact = 0usize;
        let slot_of = |p: [u32; 3], o: [u16; 3]| -> usize {
            let x = (p[0] % m + u32::from(o[0])) % m;
            let y = (p[1] % m + u32::from(o[1])) % m;
            let z = (p[2] % m + u32::from(o[2])) % m;
            x as usize + mu * (y as usize + mu * z as usize)
        };
        let fits =
            |bucket: &[[u32; 3]], o: [u16; 3], slots: &[u32]| bucket.iter().all(|&p| slots[slot_of(p, o)] == EMPTY_KEY);
        let mut coherent = 0u64;
        let mut searched = 0u64;

        for &q in &order {
            let q = q as usize;
            let bucket = &bucketed[start[q] as usize..start[q + 1] as usize];
            let mut chosen: Option<[u16; 3]> = None;
            if options.coherence {
                let (qx, qy, qz) = (q % ru, (q / ru) % ru, q / (ru * ru));
                let neighbours = [
                    ((qx + ru - 1) % ru, qy, qz),
                    ((qx + 1) % ru, qy, qz),
                    (qx, (qy + ru - 1) % ru, qz),
                    (qx, (qy + 1) % ru, qz),
                    (qx, qy, (qz + ru - 1) % ru),
                    (qx, qy, (qz + 1) % ru),
                ];
                for (x, y, z) in neighbours {
                    let nq = x + ru * (y + ru * z);
                    if assigned[nq] && fits(bucket, offsets[nq], &slots) {
                        chosen = Some(offsets[nq]);
                        coherent += 1;
                        break;
                    }
                }
            }
            if chosen.is_none() {
                if used_since_compact * 2 > free.len() {
                    free.retain(|&s| slots[s as usize] == EMPTY_KEY);
                    used_since_compact = 0;
                }
                // Try putting the bucket's first point in each free slot, from a random start.
                let p0 = bucket[0];
                let h0 = [p0[0] % m, p0[1] % m, p0[2] % m];
                let len = free.len();
                if len == 0 {
                    return None;
                }
                let first = (rng.next_u64() % len as u64) as usize;
                for i in 0..len {
                    let s = free[(first + i) % len] as usize;
                    if slots[s] != EMPTY_KEY {
                        continue;
                    }
                    let (sx, sy, sz) = ((s % mu) as u32, ((s / mu) % mu) as u32, (s / (mu * mu)) as u32);
                    let o =
                        [((sx + m - h0[0]) % m) as u16, ((sy + m - h0[1]) % m) as u16, ((sz + m - h0[2]) % m) as u16];
                    if fits(bucket, o, &slots) {
                        chosen = Some(o);
                        searched += 1;
                        break;
                    }
                }
            }
            let o = chosen?;
            for &p in bucket {
                slots[slot_of(p, o)] = pack_key(p);
            }
            used_since_compact += bucket.len();
            offsets[q] = o;
            assigned[q] = true;
        }
        stats.coherent_buckets = coherent;
        stats.searched_buckets = searched;
        Some(PshTable { u, m, r, n: points.len(), offsets, keys: slots, residues: Residues::new(u, m, r) })
    }

    /// Rebuilds a table from stored parts, checking every invariant a query relies on: sizes,
    /// offsets `< m`, keys inside the domain, each key stored in the slot it hashes to (so the
    /// table is collision-free by construction of the check).
    pub fn from_parts(u: u32, m: u32, r: u32, offsets: Vec<[u16; 3]>, keys: Vec<u32>) -> Result<PshTable, String> {
        if u == 0 || u > MAX_DOMAIN {
            return Err(format!("grid side {u} outside 1..={MAX_DOMAIN}"));
        }
        if m == 0 || m > MAX_TABLE_SIDE || r == 0 || r > MAX_TABLE_SIDE {
            return Err(format!("table sides m = {m}, r = {r} outside 1..={MAX_TABLE_SIDE}"));
        }
        let (m3, r3) = ((m as usize).pow(3), (r as usize).pow(3));
        if offsets.len() != r3 || keys.len() != m3 {
            return Err(format!("{} offsets and {} slots for r = {r}, m = {m}", offsets.len(), keys.len()));
        }
        if offsets.iter().any(|o| o.iter().any(|&c| u32::from(c) >= m)) {
            return Err("an offset is not below m".into());
        }
        let mut table = PshTable { u, m, r, n: 0, offsets, keys: Vec::new(), residues: Residues::new(u, m, r) };
        let mut n = 0;
        for (s, &k) in keys.iter().enumerate() {
            if k == EMPTY_KEY {
                continue;
            }
            let p = unpack_key(k);
            if k >> 30 != 0 || p.iter().any(|&c| c >= u) {
                return Err(format!("slot {s} holds a key outside the {u}^3 grid"));
            }
            if table.hash(p) as usize != s {
                return Err(format!("slot {s} holds a key that hashes elsewhere"));
            }
            n += 1;
        }
        table.n = n;
        table.keys = keys;
        Ok(table)
    }

    /// Grid side `u`.
    pub fn domain(&self) -> u32 {
        self.u
    }

    /// Hash table side `m` (`m^3` slots).
    pub fn table_side(&self) -> u32 {
        self.m
    }

    /// Offset table side `r` (`r^3` entries).
    pub fn offset_side(&self) -> u32 {
        self.r
    }

    /// Number of occupied voxels.
    pub fn len(&self) -> usize {
        self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Number of slots, `m^3`.
    pub fn slot_count(&self) -> usize {
        self.keys.len()
    }

    /// `Φ` (for serialisation).
    pub fn offsets(&self) -> &[[u16; 3]] {
        &self.offsets
    }

    /// Slot keys (for serialisation).
    pub fn keys(&self) -> &[u32] {
        &self.keys
    }

    /// Bytes of the two tables as stored.
    pub fn table_bytes(&self) -> usize {
        self.offsets.len() * 6 + self.keys.len() * 4
    }

    /// `h(p)` without the occupancy check (`p` inside the grid; a coordinate of `u` or more
    /// panics).
    #[inline]
    pub fn hash(&self, p: [u32; 3]) -> u32 {
        let res = &self.residues;
        let (mr, mm) = (p.map(|c| res.mod_r[c as usize]), p.map(|c| res.mod_m[c as usize]));
        self.hash_residues(mr, mm)
    }

    /// `h(p) = (p + Φ(p mod r)) mod m` (Lefebvre and Hoppe; NEPHELE section 4.3) from the
    /// residues of `p`: one offset read, and a subtraction for each `mod m` (both terms are
    /// below `m`).
    #[inline(always)]
    fn hash_residues(&self, mod_r: [u16; 3], mod_m: [u16; 3]) -> u32 {
        let (m, r) = (self.m, self.r as usize);
        let q = usize::from(mod_r[0]) + r * (usize::from(mod_r[1]) + r * usize::from(mod_r[2]));
        let o = self.offsets[q];
        let wrap = |a: u16, b: u16| {
            let s = u32::from(a) + u32::from(b);
            if s >= m { s - m } else { s }
        };
        let (x, y, z) = (wrap(mod_m[0], o[0]), wrap(mod_m[1], o[1]), wrap(mod_m[2], o[2]));
        x + m * (y + m * z)
    }

    /// The slots of the 8 voxels `b + (dx, dy, dz)`, `d* in {0, 1}`, corner `dx + 2 dy + 4 dz`,
    /// and a bit per voxel that is occupied (those outside the grid are not). The same
    /// answers as 8 calls of [`PshTable::slot_i`] (tested), without a branch on the tables'
    /// contents: the loads of one cell, and of the next cells in a batch, are in flight
    /// together (the keys' read, a cache miss on the larger tables, was 58 % of the
    /// look-up's time under `perf` when a branch waited on each).
    #[inline(always)]
    pub fn cell_slots(&self, b: [i64; 3]) -> ([u32; 8], u8) {
        let probe = self.probe_cell(b);
        (probe.slots, self.occupied(&probe))
    }

    /// The first half of [`PshTable::cell_slots`]: where the 8 voxels of cell `b` would sit
    /// (reads `Φ` only), for a caller that fetches the keys' lines before [`Self::occupied`].
    #[inline(always)]
    pub fn probe_cell(&self, b: [i64; 3]) -> CellProbe {
        let u = i64::from(self.u);
        let res = &self.residues;
        // Per axis and step d: inside the grid, the coordinate's residues and key bits
        // (a coordinate outside reads the residues of 0 and is masked out).
        let mut inside = [[false; 2]; 3];
        let mut mod_r = [[0u16; 2]; 3];
        let mut mod_m = [[0u16; 2]; 3];
        let mut coord = [[0u32; 2]; 3];
        for a in 0..3 {
            for d in 0..2 {
                let c = b[a] + d as i64;
                let ok = (0..u).contains(&c);
                let ci = if ok { c as usize } else { 0 };
                inside[a][d] = ok;
                mod_r[a][d] = res.mod_r[ci];
                mod_m[a][d] = res.mod_m[ci];
                coord[a][d] = ci as u32;
            }
        }
        let mut probe = CellProbe { slots: [0; 8], keys: [0; 8], inside: 0 };
        for c in 0..8 {
            let (dx, dy, dz) = (c & 1, (c >> 1) & 1, c >> 2);
            probe.slots[c] = self
                .hash_residues([mod_r[0][dx], mod_r[1][dy], mod_r[2][dz]], [mod_m[0][dx], mod_m[1][dy], mod_m[2][dz]]);
            probe.keys[c] = pack_key([coord[0][dx], coord[1][dy], coord[2][dz]]);
            probe.inside |= u8::from(inside[0][dx] & inside[1][dy] & inside[2][dz]) << c;
        }
        probe
    }

    /// The second half of [`PshTable::cell_slots`]: a bit per voxel of the probe that is
    /// occupied (reads the 8 keys).
    #[inline(always)]
    pub fn occupied(&self, probe: &CellProbe) -> u8 {
        let mut stored = 0u8;
        for c in 0..8 {
            stored |= u8::from(self.keys[probe.slots[c] as usize] == probe.keys[c]) << c;
        }
        stored & probe.inside
    }

    /// Indices into [`PshTable::offsets`] that [`PshTable::probe_cell`] reads for cell `b`
    /// (to fetch their lines ahead).
    #[inline(always)]
    pub fn offset_indices(&self, b: [i64; 3]) -> [usize; 8] {
        let (u, r) = (i64::from(self.u), self.r as usize);
        let residue = |c: i64| if (0..u).contains(&c) { usize::from(self.residues.mod_r[c as usize]) } else { 0 };
        let mut out = [0usize; 8];
        for (c, q) in out.iter_mut().enumerate() {
            let (dx, dy, dz) = ((c & 1) as i64, ((c >> 1) & 1) as i64, (c >> 2) as i64);
            *q = residue(b[0] + dx) + r * (residue(b[1] + dy) + r * residue(b[2] + dz));
        }
        out
    }

    /// The slot of an occupied voxel, `None` for a voxel that is not occupied or lies outside
    /// the grid.
    #[inline]
    pub fn slot(&self, p: [u32; 3]) -> Option<u32> {
        if p[0] >= self.u || p[1] >= self.u || p[2] >= self.u {
            return None;
        }
        let s = self.hash(p);
        (self.keys[s as usize] == pack_key(p)).then_some(s)
    }

    /// Same as [`PshTable::slot`] for signed coordinates (neighbour look-ups at the border).
    #[inline]
    pub fn slot_i(&self, p: [i32; 3]) -> Option<u32> {
        if p.iter().any(|&c| c < 0) {
            return None;
        }
        self.slot([p[0] as u32, p[1] as u32, p[2] as u32])
    }

    /// Occupied voxels, in slot order.
    pub fn points(&self) -> impl Iterator<Item = [u32; 3]> + '_ {
        self.keys.iter().filter(|&&k| k != EMPTY_KEY).map(|&k| unpack_key(k))
    }

    /// Coherence (paper section 4.3): among pairs of occupied voxels that are neighbours
    /// along an axis, `(coherent, pairs)` where coherent pairs sit in neighbouring slots along
    /// the same axis of the `m^3` table (`h(p + e) = h(p) + e mod m`).
    pub fn coherence(&self) -> (u64, u64) {
        let m = self.m;
        let (mut coherent, mut pairs) = (0u64, 0u64);
        for p in self.points() {
            let Some(s) = self.slot(p) else { continue };
            let sc = [s % m, (s / m) % m, s / (m * m)];
            for axis in 0..3 {
                let mut q = p;
                q[axis] += 1;
                if let Some(t) = self.slot(q) {
                    pairs += 1;
                    let mut expect = sc;
                    expect[axis] = (expect[axis] + 1) % m;
                    coherent += u64::from(t == expect[0] + m * (expect[1] + m * expect[2]));
                }
            }
        }
        (coherent, pairs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::HashSet;

    /// Checks perfection exhaustively: every occupied voxel has its own slot, every other
    /// voxel of the grid is rejected.
    fn assert_perfect(table: &PshTable, points: &[[u32; 3]]) {
        let set: HashSet<[u32; 3]> = points.iter().copied().collect();
        let mut seen = HashSet::new();
        for p in &set {
            let s = table.slot(*p).expect("occupied voxel must be found");
            assert!(seen.insert(s), "collision at slot {s}");
        }
        assert_eq!(table.len(), set.len());
        assert_eq!(table.keys().iter().filter(|&&k| k != EMPTY_KEY).count(), set.len());
        let u = table.domain();
        if u <= 48 {
            for z in 0..u {
                for y in 0..u {
                    for x in 0..u {
                        if !set.contains(&[x, y, z]) {
                            assert_eq!(table.slot([x, y, z]), None, "unoccupied voxel accepted");
                        }
                    }
                }
            }
        }
        assert_eq!(table.slot([u, 0, 0]), None);
        assert_eq!(table.slot_i([-1, 0, 0]), None);
        // A cell's 8 corners at once: every cell of a small grid (those sticking out of it
        // included), else the cells around the points.
        let u = i64::from(u);
        if u <= 24 {
            for z in -1..=u {
                for y in -1..=u {
                    for x in -1..=u {
                        assert_cell_agrees(table, [x, y, z]);
                    }
                }
            }
        } else {
            for p in points.iter().take(2000) {
                for d in [-1i64, 0] {
                    assert_cell_agrees(table, p.map(|c| i64::from(c) + d));
                }
            }
        }
    }

    /// [`PshTable::cell_slots`] answers what 8 calls of `slot_i` answer.
    fn assert_cell_agrees(table: &PshTable, b: [i64; 3]) {
        let (slots, stored) = table.cell_slots(b);
        for c in 0..8 {
            let v = [b[0] + (c & 1), b[1] + ((c >> 1) & 1), b[2] + (c >> 2)].map(|x| x as i32);
            let expected = table.slot_i(v);
            let got = (stored & (1 << c) != 0).then_some(slots[c as usize]);
            assert_eq!(got, expected, "cell {b:?}, corner {c}");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn random_occupancies_have_no_collision(
            u in 1u32..40,
            density in 0.0f64..1.0,
            seed in any::<u64>(),
            factor in 1.0f32..1.6,
        ) {
            let mut rng = SplitMix64::new(seed);
            let mut points = Vec::new();
            for z in 0..u { for y in 0..u { for x in 0..u {
                if rng.next_f64() <= density * density {
                    points.push([x, y, z]);
                }
            }}}
            let options = PshOptions { table_factor: factor, seed, ..PshOptions::default() };
            let (table, _) = PshTable::build(u, &points, &options).expect("build");
            assert_perfect(&table, &points);
            // The stored parts pass the loader's validation.
            let again = PshTable::from_parts(u, table.table_side(), table.offset_side(), table.offsets().to_vec(), table.keys().to_vec());
            prop_assert_eq!(again.as_ref(), Ok(&table));
        }

        #[test]
        fn random_sparse_points_in_large_grid(seed in any::<u64>(), n in 0usize..3000) {
            let mut rng = SplitMix64::new(seed);
            let points: Vec<[u32; 3]> = (0..n).map(|_| {
                let v = rng.next_u64();
                [(v % 1024) as u32, ((v >> 10) % 1024) as u32, ((v >> 20) % 1024) as u32]
            }).collect();
            let (table, _) = PshTable::build(1024, &points, &PshOptions { seed, ..PshOptions::default() }).expect("build");
            assert_perfect(&table, &points);
        }
    }

    #[test]
    fn empty_and_full_grids() {
        let (empty, _) = PshTable::build(8, &[], &PshOptions::default()).expect("empty");
        assert!(empty.is_empty());
        assert_eq!(empty.slot([0, 0, 0]), None);
        let full: Vec<[u32; 3]> = (0..512).map(|i| [i % 8, (i / 8) % 8, i / 64]).collect();
        let (table, _) =
            PshTable::build(8, &full, &PshOptions { table_factor: 1.0, ..PshOptions::default() }).expect("full");
        assert_perfect(&table, &full);
        assert_eq!(table.slot_count(), 512, "a full grid packs into exactly n slots");
    }

    #[test]
    fn bad_input_is_an_error() {
        assert_eq!(PshTable::build(0, &[], &PshOptions::default()), Err(PshError::BadDomain(0)));
        assert!(matches!(PshTable::build(4, &[[4, 0, 0]], &PshOptions::default()), Err(PshError::PointOutside { .. })));
        let bad = PshOptions { table_factor: 0.5, ..PshOptions::default() };
        assert!(matches!(PshTable::build(4, &[[1, 0, 0]], &bad), Err(PshError::BadOption(_))));
    }

    #[test]
    fn from_parts_rejects_inconsistent_tables() {
        let points = [[1, 2, 3], [4, 5, 6], [7, 0, 1]];
        let (t, _) = PshTable::build(8, &points, &PshOptions::default()).expect("build");
        let (u, m, r) = (t.domain(), t.table_side(), t.offset_side());
        let mut keys = t.keys().to_vec();
        let s = t.slot([1, 2, 3]).expect("slot") as usize;
        let other = (s + 1) % keys.len();
        keys.swap(s, other);
        assert!(PshTable::from_parts(u, m, r, t.offsets().to_vec(), keys).is_err(), "a key in the wrong slot");
        let mut offsets = t.offsets().to_vec();
        offsets[0] = [m as u16, 0, 0];
        assert!(PshTable::from_parts(u, m, r, offsets, t.keys().to_vec()).is_err(), "offset out of range");
        assert!(PshTable::from_parts(u, m, r, vec![], t.keys().to_vec()).is_err(), "wrong sizes");
    }

    /// A surface-like occupancy (a sphere shell) hashes coherently: a large share of
    /// neighbouring voxels land in neighbouring slots, far above chance (~0).
    #[test]
    fn shell_is_coherent() {
        let u = 64u32;
        let c = u as f32 / 2.0;
        let mut points = Vec::new();
        for z in 0..u {
            for y in 0..u {
                for x in 0..u {
                    let d = ((x as f32 - c).powi(2) + (y as f32 - c).powi(2) + (z as f32 - c).powi(2)).sqrt();
                    if (d - 25.0).abs() < 1.0 {
                        points.push([x, y, z]);
                    }
                }
            }
        }
        let (table, stats) = PshTable::build(u, &points, &PshOptions::coherent()).expect("build");
        assert_perfect(&table, &points);
        let (coherent, pairs) = table.coherence();
        let fraction = coherent as f64 / pairs as f64;
        eprintln!(
            "shell: n = {}, m = {}, r = {}, coherence {fraction:.3}, {stats:?}",
            points.len(),
            table.table_side(),
            table.offset_side()
        );
        assert!(fraction > 0.3, "coherence {fraction}");
        let (table, _) =
            PshTable::build(u, &points, &PshOptions { coherence: false, ..PshOptions::coherent() }).expect("build");
        let (c2, p2) = table.coherence();
        assert!((c2 as f64 / p2 as f64) < fraction / 2.0, "the heuristic must matter");
    }
}
