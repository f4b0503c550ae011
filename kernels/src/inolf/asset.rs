//! The i-NOLF asset file (`.nolf`): one versioned binary file holding everything a worker
//! needs to render an object.
//!
//! Layout (all integers and floats little-endian):
//!
//! ```text
//! 0   magic        8 bytes  "NOLF\r\n\x1a\n" (catches text-mode and truncation damage, as PNG)
//! 8   version      u32      FORMAT_VERSION
//! 12  sections     u32      number of section-table entries (<= MAX_SECTIONS)
//! 16  file length  u64      total length of the file in bytes
//! 24  table crc    u32      CRC-32 of bytes 0..24 followed by the section table
//! 28  flags        u32      0
//! 32  section table: per section 32 bytes
//!       kind u32, flags u32 (0), offset u64, length u64, crc32 u32 (of the payload), 0 u32
//! ... section payloads (8-byte aligned, in any order, never overlapping)
//! ```
//!
//! Sections: `Meta` (UTF-8 JSON), `DensityCubes` (required), `DiffuseCubes`, `Psh` (the
//! perfect spatial hash and its feature table) and `Tensors` (named MLP weights).
//!
//! Loading is defensive: the file length is checked before the file is read, and every
//! count and size read from the file is checked against the bytes actually present and
//! against fixed limits *before* anything is allocated for it, so a hostile file cannot
//! make the loader allocate more than a small multiple of its own length. Every failure
//! is a typed [`AssetError`].

use std::path::Path;

use glam::Vec3;
use thiserror::Error;

use super::cubes::{DensityCubes, EMPTY_CELL, MAX_CELLS, MAX_CHANNELS, MAX_CUBE_RES, MAX_GRID_SIDE, SparseCubes};
use super::encoding::PshEncoding;
use super::psh::{MAX_DOMAIN, MAX_TABLE_SIDE, PshTable};

/// First eight bytes of every asset.
pub const MAGIC: [u8; 8] = *b"NOLF\r\n\x1a\n";
/// The version this code writes and reads.
pub const FORMAT_VERSION: u32 = 1;
/// Largest asset accepted, bytes.
pub const MAX_FILE_BYTES: u64 = 4 << 30;
/// Most section-table entries.
pub const MAX_SECTIONS: u32 = 16;
/// Most tensors in the `Tensors` section.
pub const MAX_TENSORS: u32 = 256;
/// Most elements of one tensor.
pub const MAX_TENSOR_ELEMENTS: u64 = 1 << 26;
/// Longest tensor name, bytes.
pub const MAX_NAME_BYTES: u32 = 256;
/// Largest `Meta` section, bytes.
pub const MAX_META_BYTES: u64 = 1 << 20;
/// Most hash-table slots of the PSH section.
pub const MAX_PSH_SLOTS: u64 = 1 << 26;
/// Longest feature vector per PSH slot.
pub const MAX_FEATURE_DIM: u32 = 64;

const HEADER_LEN: usize = 32;
const ENTRY_LEN: usize = 32;

/// What a section holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum SectionKind {
    Meta = 1,
    DensityCubes = 2,
    DiffuseCubes = 3,
    Psh = 4,
    Tensors = 5,
}

impl SectionKind {
    fn from_u32(v: u32) -> Option<SectionKind> {
        Some(match v {
            1 => SectionKind::Meta,
            2 => SectionKind::DensityCubes,
            3 => SectionKind::DiffuseCubes,
            4 => SectionKind::Psh,
            5 => SectionKind::Tensors,
            _ => return None,
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            SectionKind::Meta => "meta",
            SectionKind::DensityCubes => "density cubes",
            SectionKind::DiffuseCubes => "diffuse cubes",
            SectionKind::Psh => "perfect spatial hash",
            SectionKind::Tensors => "tensors",
        }
    }
}

/// Why an asset could not be read or written.
#[derive(Debug, Error)]
pub enum AssetError {
    #[error("cannot read or write the asset: {0}")]
    Io(#[from] std::io::Error),
    #[error("not a .nolf asset (bad magic bytes)")]
    NotAnAsset,
    #[error("asset format version {found} is not supported (this build reads version {supported})")]
    UnsupportedVersion { found: u32, supported: u32 },
    #[error("asset is truncated: {needed} bytes needed, {available} present")]
    Truncated { needed: u64, available: u64 },
    #[error("asset header says {header} bytes but the file has {actual} (trailing data)")]
    LengthMismatch { header: u64, actual: u64 },
    #[error("{what} is {value}, above the limit of {limit}")]
    TooLarge { what: &'static str, value: u64, limit: u64 },
    #[error("section table checksum mismatch (stored {stored:#010x}, computed {computed:#010x})")]
    TableChecksum { stored: u32, computed: u32 },
    #[error("unknown section kind {0}")]
    UnknownSection(u32),
    #[error("section {0} appears twice")]
    DuplicateSection(&'static str),
    #[error("required section {0} is missing")]
    MissingSection(&'static str),
    #[error("section {section} (bytes {offset}..+{length}) lies outside the {file_len}-byte file or over the header")]
    SectionOutOfBounds { section: &'static str, offset: u64, length: u64, file_len: u64 },
    #[error("sections {first} and {second} overlap")]
    OverlappingSections { first: &'static str, second: &'static str },
    #[error("section {section} is corrupt (checksum stored {stored:#010x}, computed {computed:#010x})")]
    SectionChecksum { section: &'static str, stored: u32, computed: u32 },
    #[error("section {section} is malformed: {reason}")]
    Malformed { section: &'static str, reason: String },
}

/// Named weights of a network (row-major, shape as stored).
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    pub name: String,
    pub shape: Vec<u32>,
    pub data: Vec<f32>,
}

/// Everything a worker needs to render one i-NOLF object.
#[derive(Debug, Clone, PartialEq)]
pub struct Asset {
    /// Free-form JSON (scene name, bake settings, quality reached).
    pub meta: String,
    pub density: DensityCubes,
    /// Diffuse colour and specular tint baked around the hit surfaces.
    pub diffuse: Option<SparseCubes>,
    pub psh: Option<PshEncoding>,
    pub tensors: Vec<Tensor>,
}

/// Size of each part as written, for the bake summary.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AssetSizes {
    pub parts: Vec<(&'static str, u64)>,
    pub total: u64,
}

// ---------------------------------------------------------------------------------------
// Writing

#[derive(Debug, Default)]
struct Writer(Vec<u8>);

impl Writer {
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn vec3(&mut self, v: Vec3) {
        v.to_array().iter().for_each(|&x| self.f32(x));
    }
}

fn encode_cubes(c: &SparseCubes) -> Vec<u8> {
    let mut w = Writer::default();
    w.vec3(c.min());
    w.f32(c.cell());
    c.dims().iter().for_each(|&d| w.u32(d));
    w.u32(c.cube_res());
    w.u32(c.channels());
    w.u32(c.cube_count() as u32);
    c.index().iter().for_each(|&e| w.u32(e));
    w.0.extend_from_slice(c.data());
    w.0
}

fn encode_psh(p: &PshEncoding) -> Vec<u8> {
    let mut w = Writer::default();
    let t = &p.table;
    w.u32(t.domain());
    w.u32(t.table_side());
    w.u32(t.offset_side());
    w.vec3(p.origin);
    w.f32(p.voxel);
    w.u32(p.feature_dim);
    for o in t.offsets() {
        o.iter().for_each(|&c| w.0.extend_from_slice(&c.to_le_bytes()));
    }
    t.keys().iter().for_each(|&k| w.u32(k));
    p.features.iter().for_each(|&f| w.f32(f));
    w.0
}

fn encode_tensors(tensors: &[Tensor]) -> Vec<u8> {
    let mut w = Writer::default();
    w.u32(tensors.len() as u32);
    for t in tensors {
        w.u32(t.name.len() as u32);
        w.0.extend_from_slice(t.name.as_bytes());
        w.u32(t.shape.len() as u32);
        t.shape.iter().for_each(|&d| w.u32(d));
        t.data.iter().for_each(|&x| w.f32(x));
    }
    w.0
}

impl Asset {
    /// Checks what the reader will check, so that a written asset always loads.
    fn check_writable(&self) -> Result<(), AssetError> {
        let malformed =
            |section: SectionKind, reason: String| AssetError::Malformed { section: section.name(), reason };
        if self.meta.len() as u64 > MAX_META_BYTES {
            return Err(AssetError::TooLarge {
                what: "meta section",
                value: self.meta.len() as u64,
                limit: MAX_META_BYTES,
            });
        }
        if let Some(p) = &self.psh {
            if p.feature_dim > MAX_FEATURE_DIM
                || p.features.len() as u64 != p.table.slot_count() as u64 * u64::from(p.feature_dim)
            {
                return Err(malformed(SectionKind::Psh, "feature table does not match the slots".into()));
            }
            if !(p.origin.is_finite() && p.voxel.is_finite() && p.voxel > 0.0) {
                return Err(malformed(SectionKind::Psh, "lattice origin/spacing not finite".into()));
            }
        }
        if self.tensors.len() as u64 > u64::from(MAX_TENSORS) {
            return Err(malformed(SectionKind::Tensors, "too many tensors".into()));
        }
        for t in &self.tensors {
            let count = t.shape.iter().map(|&d| u64::from(d)).product::<u64>();
            if t.name.len() as u64 > u64::from(MAX_NAME_BYTES)
                || t.shape.is_empty()
                || t.shape.len() > 4
                || count != t.data.len() as u64
                || count > MAX_TENSOR_ELEMENTS
            {
                return Err(malformed(SectionKind::Tensors, format!("tensor {:?} is inconsistent", t.name)));
            }
        }
        Ok(())
    }

    /// Encodes the asset.
    pub fn to_bytes(&self) -> Result<Vec<u8>, AssetError> {
        self.check_writable()?;
        let mut sections: Vec<(SectionKind, Vec<u8>)> = vec![(SectionKind::Meta, self.meta.as_bytes().to_vec())];
        sections.push((SectionKind::DensityCubes, encode_cubes(self.density.cubes())));
        if let Some(d) = &self.diffuse {
            sections.push((SectionKind::DiffuseCubes, encode_cubes(d)));
        }
        if let Some(p) = &self.psh {
            sections.push((SectionKind::Psh, encode_psh(p)));
        }
        if !self.tensors.is_empty() {
            sections.push((SectionKind::Tensors, encode_tensors(&self.tensors)));
        }
        let table_end = HEADER_LEN + ENTRY_LEN * sections.len();
        let mut out = vec![0u8; table_end];
        let mut entries = Vec::new();
        for (kind, payload) in &sections {
            while !out.len().is_multiple_of(8) {
                out.push(0);
            }
            entries.push((*kind, out.len() as u64, payload.len() as u64, crc32fast::hash(payload)));
            out.extend_from_slice(payload);
        }
        out[0..8].copy_from_slice(&MAGIC);
        out[8..12].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        out[12..16].copy_from_slice(&(sections.len() as u32).to_le_bytes());
        let len = out.len() as u64;
        out[16..24].copy_from_slice(&len.to_le_bytes());
        for (i, (kind, offset, length, crc)) in entries.into_iter().enumerate() {
            let e = &mut out[HEADER_LEN + i * ENTRY_LEN..HEADER_LEN + (i + 1) * ENTRY_LEN];
            e[0..4].copy_from_slice(&(kind as u32).to_le_bytes());
            e[8..16].copy_from_slice(&offset.to_le_bytes());
            e[16..24].copy_from_slice(&length.to_le_bytes());
            e[24..28].copy_from_slice(&crc.to_le_bytes());
        }
        let crc = table_crc(&out, table_end);
        out[24..28].copy_from_slice(&crc.to_le_bytes());
        Ok(out)
    }

    /// Bytes of each part as encoded.
    pub fn sizes(&self) -> AssetSizes {
        let mut parts =
            vec![("meta", self.meta.len() as u64), ("density cubes", encode_cubes(self.density.cubes()).len() as u64)];
        if let Some(d) = &self.diffuse {
            parts.push(("diffuse cubes", encode_cubes(d).len() as u64));
        }
        if let Some(p) = &self.psh {
            let tables = p.table.table_bytes() as u64;
            parts.push(("psh tables", tables));
            parts.push(("psh features", p.features.len() as u64 * 4));
        }
        if !self.tensors.is_empty() {
            parts.push(("mlp weights", encode_tensors(&self.tensors).len() as u64));
        }
        let total = parts.iter().map(|p| p.1).sum::<u64>();
        AssetSizes { parts, total }
    }

    /// Writes the asset atomically (temporary file in the same folder, then rename).
    pub fn save(&self, path: &Path) -> Result<(), AssetError> {
        let bytes = self.to_bytes()?;
        let tmp = path.with_extension("nolf.tmp");
        std::fs::write(&tmp, &bytes)?;
        std::fs::rename(&tmp, path)?;
        Ok(())
    }

    /// Reads and validates an asset file (size checked before reading).
    pub fn load(path: &Path) -> Result<Asset, AssetError> {
        let len = std::fs::metadata(path)?.len();
        if len > MAX_FILE_BYTES {
            return Err(AssetError::TooLarge { what: "asset file", value: len, limit: MAX_FILE_BYTES });
        }
        Asset::from_bytes(&std::fs::read(path)?)
    }

    /// Decodes and validates an asset held in memory.
    pub fn from_bytes(bytes: &[u8]) -> Result<Asset, AssetError> {
        let sections = read_table(bytes)?;
        let mut meta = None;
        let mut density = None;
        let mut diffuse = None;
        let mut psh = None;
        let mut tensors = None;
        for (kind, payload) in sections {
            match kind {
                SectionKind::Meta => meta = Some(decode_meta(payload)?),
                SectionKind::DensityCubes => {
                    let cubes = decode_cubes(payload, kind)?;
                    density = Some(
                        DensityCubes::from_cubes(cubes)
                            .map_err(|e| AssetError::Malformed { section: kind.name(), reason: e.to_string() })?,
                    );
                }
                SectionKind::DiffuseCubes => diffuse = Some(decode_cubes(payload, kind)?),
                SectionKind::Psh => psh = Some(decode_psh(payload)?),
                SectionKind::Tensors => tensors = Some(decode_tensors(payload)?),
            }
        }
        Ok(Asset {
            meta: meta.unwrap_or_default(),
            density: density.ok_or(AssetError::MissingSection(SectionKind::DensityCubes.name()))?,
            diffuse,
            psh,
            tensors: tensors.unwrap_or_default(),
        })
    }
}

fn table_crc(bytes: &[u8], table_end: usize) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(&bytes[0..24]);
    h.update(&bytes[HEADER_LEN..table_end]);
    h.finalize()
}

fn le_u32(b: &[u8], at: usize) -> u32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[at..at + 4]);
    u32::from_le_bytes(a)
}

fn le_u64(b: &[u8], at: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(a)
}

/// Validates the header and the section table; returns each section's payload.
fn read_table(bytes: &[u8]) -> Result<Vec<(SectionKind, &[u8])>, AssetError> {
    let available = bytes.len() as u64;
    if bytes.len() < MAGIC.len() {
        return Err(if MAGIC.starts_with(bytes) {
            AssetError::Truncated { needed: HEADER_LEN as u64, available }
        } else {
            AssetError::NotAnAsset
        });
    }
    if bytes[0..8] != MAGIC {
        return Err(AssetError::NotAnAsset);
    }
    if bytes.len() < HEADER_LEN {
        return Err(AssetError::Truncated { needed: HEADER_LEN as u64, available });
    }
    let version = le_u32(bytes, 8);
    if version != FORMAT_VERSION {
        return Err(AssetError::UnsupportedVersion { found: version, supported: FORMAT_VERSION });
    }
    let count = le_u32(bytes, 12);
    let file_len = le_u64(bytes, 16);
    if file_len > MAX_FILE_BYTES {
        return Err(AssetError::TooLarge { what: "asset length", value: file_len, limit: MAX_FILE_BYTES });
    }
    if file_len > available {
        return Err(AssetError::Truncated { needed: file_len, available });
    }
    if file_len < available {
        return Err(AssetError::LengthMismatch { header: file_len, actual: available });
    }
    if count > MAX_SECTIONS {
        return Err(AssetError::TooLarge {
            what: "section count",
            value: u64::from(count),
            limit: u64::from(MAX_SECTIONS),
        });
    }
    let table_end = HEADER_LEN + ENTRY_LEN * count as usize;
    if bytes.len() < table_end {
        return Err(AssetError::Truncated { needed: table_end as u64, available });
    }
    let stored = le_u32(bytes, 24);
    let computed = table_crc(bytes, table_end);
    if stored != computed {
        return Err(AssetError::TableChecksum { stored, computed });
    }
    if le_u32(bytes, 28) != 0 {
        return Err(AssetError::Malformed { section: "header", reason: "unknown header flags".into() });
    }
    let mut entries: Vec<(SectionKind, u64, u64, u32)> = Vec::with_capacity(count as usize);
    for i in 0..count as usize {
        let e = &bytes[HEADER_LEN + i * ENTRY_LEN..HEADER_LEN + (i + 1) * ENTRY_LEN];
        let raw_kind = le_u32(e, 0);
        let kind = SectionKind::from_u32(raw_kind).ok_or(AssetError::UnknownSection(raw_kind))?;
        if le_u32(e, 4) != 0 || le_u32(e, 28) != 0 {
            return Err(AssetError::Malformed { section: kind.name(), reason: "unknown section flags".into() });
        }
        let (offset, length, crc) = (le_u64(e, 8), le_u64(e, 16), le_u32(e, 24));
        let end = offset.checked_add(length);
        if offset < table_end as u64 || end.is_none_or(|end| end > file_len) {
            return Err(AssetError::SectionOutOfBounds { section: kind.name(), offset, length, file_len });
        }
        if entries.iter().any(|x| x.0 == kind) {
            return Err(AssetError::DuplicateSection(kind.name()));
        }
        entries.push((kind, offset, length, crc));
    }
    let mut by_offset = entries.clone();
    by_offset.sort_by_key(|e| (e.1, e.2));
    for pair in by_offset.windows(2) {
        if pair[0].1 + pair[0].2 > pair[1].1 {
            return Err(AssetError::OverlappingSections { first: pair[0].0.name(), second: pair[1].0.name() });
        }
    }
    let mut out = Vec::with_capacity(entries.len());
    for (kind, offset, length, stored) in entries {
        let payload = &bytes[offset as usize..(offset + length) as usize];
        let computed = crc32fast::hash(payload);
        if computed != stored {
            return Err(AssetError::SectionChecksum { section: kind.name(), stored, computed });
        }
        out.push((kind, payload));
    }
    Ok(out)
}

/// Recomputes the table and section checksums of an encoded asset in place (so that tests
/// and fuzzers can reach the section parsers with mutated payloads). Returns `false` when
/// the header or table is too broken to locate the sections.
pub fn reseal_checksums(bytes: &mut [u8]) -> bool {
    if bytes.len() < HEADER_LEN {
        return false;
    }
    let count = le_u32(bytes, 12).min(MAX_SECTIONS) as usize;
    let table_end = HEADER_LEN + ENTRY_LEN * count;
    if bytes.len() < table_end {
        return false;
    }
    for i in 0..count {
        let at = HEADER_LEN + i * ENTRY_LEN;
        let (offset, length) = (le_u64(bytes, at + 8), le_u64(bytes, at + 16));
        if let Some(end) = offset.checked_add(length).filter(|&e| e <= bytes.len() as u64) {
            let crc = crc32fast::hash(&bytes[offset as usize..end as usize]);
            bytes[at + 24..at + 28].copy_from_slice(&crc.to_le_bytes());
        }
    }
    let crc = table_crc(bytes, table_end);
    bytes[24..28].copy_from_slice(&crc.to_le_bytes());
    true
}

// ---------------------------------------------------------------------------------------
// Section parsers: every count is checked against the bytes left before allocating.

#[derive(Debug)]
struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
    section: &'static str,
}

impl<'a> Reader<'a> {
    fn new(buf: &'a [u8], kind: SectionKind) -> Reader<'a> {
        Reader { buf, pos: 0, section: kind.name() }
    }

    fn malformed(&self, reason: impl Into<String>) -> AssetError {
        AssetError::Malformed { section: self.section, reason: reason.into() }
    }

    fn remaining(&self) -> u64 {
        (self.buf.len() - self.pos) as u64
    }

    fn take(&mut self, n: u64) -> Result<&'a [u8], AssetError> {
        if n > self.remaining() {
            return Err(self.malformed(format!("needs {n} more bytes, {} left", self.remaining())));
        }
        let s = &self.buf[self.pos..self.pos + n as usize];
        self.pos += n as usize;
        Ok(s)
    }

    fn u32(&mut self) -> Result<u32, AssetError> {
        Ok(le_u32(self.take(4)?, 0))
    }

    fn f32(&mut self) -> Result<f32, AssetError> {
        Ok(f32::from_bits(self.u32()?))
    }

    fn vec3(&mut self) -> Result<Vec3, AssetError> {
        Ok(Vec3::new(self.f32()?, self.f32()?, self.f32()?))
    }

    /// Reserves `count` elements of `size` bytes: fails before any allocation if the
    /// section does not hold them.
    fn array(&mut self, count: u64, size: u64) -> Result<&'a [u8], AssetError> {
        let bytes = count.checked_mul(size).ok_or_else(|| self.malformed("size overflows"))?;
        self.take(bytes)
    }

    fn u32s(&mut self, count: u64) -> Result<Vec<u32>, AssetError> {
        Ok(self.array(count, 4)?.chunks_exact(4).map(|c| le_u32(c, 0)).collect())
    }

    fn f32s(&mut self, count: u64) -> Result<Vec<f32>, AssetError> {
        Ok(self.array(count, 4)?.chunks_exact(4).map(|c| f32::from_bits(le_u32(c, 0))).collect())
    }

    fn finish(&self) -> Result<(), AssetError> {
        match self.remaining() {
            0 => Ok(()),
            n => Err(self.malformed(format!("{n} unexplained bytes at the end"))),
        }
    }
}

fn limit(what: &'static str, value: u64, max: u64) -> Result<(), AssetError> {
    if value > max { Err(AssetError::TooLarge { what, value, limit: max }) } else { Ok(()) }
}

fn decode_meta(payload: &[u8]) -> Result<String, AssetError> {
    limit("meta section", payload.len() as u64, MAX_META_BYTES)?;
    let text =
        std::str::from_utf8(payload).map_err(|e| AssetError::Malformed { section: "meta", reason: e.to_string() })?;
    if !text.is_empty() {
        serde_json::from_str::<serde_json::Value>(text)
            .map_err(|e| AssetError::Malformed { section: "meta", reason: e.to_string() })?;
    }
    Ok(text.to_owned())
}

fn decode_cubes(payload: &[u8], kind: SectionKind) -> Result<SparseCubes, AssetError> {
    let mut r = Reader::new(payload, kind);
    let min = r.vec3()?;
    let cell = r.f32()?;
    let dims = [r.u32()?, r.u32()?, r.u32()?];
    let cube_res = r.u32()?;
    let channels = r.u32()?;
    let count = r.u32()?;
    for &d in &dims {
        limit("grid side", u64::from(d), u64::from(MAX_GRID_SIDE))?;
    }
    let cells = dims.iter().map(|&d| u64::from(d)).product::<u64>();
    limit("cell count", cells, MAX_CELLS)?;
    limit("cube side", u64::from(cube_res), u64::from(MAX_CUBE_RES))?;
    limit("channels", u64::from(channels), u64::from(MAX_CHANNELS))?;
    limit("cube count", u64::from(count), cells)?;
    let index = r.u32s(cells)?;
    let cube_bytes = u64::from(cube_res).pow(3) * u64::from(channels);
    let data = r.array(u64::from(count), cube_bytes)?.to_vec();
    r.finish()?;
    if index.iter().any(|&e| e != EMPTY_CELL && e >= count) {
        return Err(r.malformed("index entry past the cube table"));
    }
    SparseCubes::from_parts(min, cell, dims, cube_res, channels, index, data).map_err(|e| r.malformed(e.to_string()))
}

fn decode_psh(payload: &[u8]) -> Result<PshEncoding, AssetError> {
    let mut r = Reader::new(payload, SectionKind::Psh);
    let u = r.u32()?;
    let m = r.u32()?;
    let rr = r.u32()?;
    let origin = r.vec3()?;
    let voxel = r.f32()?;
    let feature_dim = r.u32()?;
    limit("psh grid side", u64::from(u), u64::from(MAX_DOMAIN))?;
    limit("psh table side", u64::from(m), u64::from(MAX_TABLE_SIDE))?;
    limit("psh offset table side", u64::from(rr), u64::from(MAX_TABLE_SIDE))?;
    limit("psh feature size", u64::from(feature_dim), u64::from(MAX_FEATURE_DIM))?;
    let slots = u64::from(m).pow(3);
    let entries = u64::from(rr).pow(3);
    limit("psh slots", slots, MAX_PSH_SLOTS)?;
    limit("psh offsets", entries, MAX_PSH_SLOTS)?;
    if !(origin.is_finite() && voxel.is_finite() && voxel > 0.0) {
        return Err(r.malformed("lattice origin/spacing not finite"));
    }
    let offsets: Vec<[u16; 3]> = r
        .array(entries, 6)?
        .chunks_exact(6)
        .map(|c| [u16::from_le_bytes([c[0], c[1]]), u16::from_le_bytes([c[2], c[3]]), u16::from_le_bytes([c[4], c[5]])])
        .collect();
    let keys = r.u32s(slots)?;
    let features = r.f32s(slots * u64::from(feature_dim))?;
    r.finish()?;
    if features.iter().any(|f| !f.is_finite()) {
        return Err(r.malformed("non-finite feature"));
    }
    let table = PshTable::from_parts(u, m, rr, offsets, keys).map_err(|e| r.malformed(e))?;
    Ok(PshEncoding { table, origin, voxel, feature_dim, features })
}

fn decode_tensors(payload: &[u8]) -> Result<Vec<Tensor>, AssetError> {
    let mut r = Reader::new(payload, SectionKind::Tensors);
    let count = r.u32()?;
    limit("tensor count", u64::from(count), u64::from(MAX_TENSORS))?;
    let mut out = Vec::new();
    for _ in 0..count {
        let name_len = r.u32()?;
        limit("tensor name length", u64::from(name_len), u64::from(MAX_NAME_BYTES))?;
        let name = std::str::from_utf8(r.take(u64::from(name_len))?)
            .map_err(|_| r.malformed("tensor name is not UTF-8"))?
            .to_owned();
        let ndim = r.u32()?;
        if !(1..=4).contains(&ndim) {
            return Err(r.malformed(format!("tensor {name:?} has {ndim} dimensions")));
        }
        let mut shape = Vec::new();
        for _ in 0..ndim {
            shape.push(r.u32()?);
        }
        let elements = shape
            .iter()
            .try_fold(1u64, |acc, &d| acc.checked_mul(u64::from(d)))
            .ok_or_else(|| r.malformed("tensor size overflows"))?;
        limit("tensor elements", elements, MAX_TENSOR_ELEMENTS)?;
        let data = r.f32s(elements)?;
        if data.iter().any(|x| !x.is_finite()) {
            return Err(r.malformed(format!("tensor {name:?} holds a non-finite weight")));
        }
        out.push(Tensor { name, shape, data });
    }
    r.finish()?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inolf::cubes::CubeOptions;
    use crate::inolf::psh::PshOptions;
    use nephele_geometry::Bounds;
    use proptest::prelude::*;

    fn sample_asset() -> Asset {
        let options = CubeOptions { resolution: 6, cube_res: 4, probe: 2, dilate: 0 };
        let bounds = Bounds { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) };
        let density = DensityCubes::build(
            bounds,
            &options,
            |p: &[Vec3], out: &mut [f32]| {
                p.iter().zip(out).for_each(|(p, o)| *o = if p.length() < 0.6 { 50.0 } else { 0.0 })
            },
            &|_| {},
        )
        .expect("cubes");
        let c = density.cubes();
        let diffuse_data: Vec<u8> = (0..c.cube_count() * 64 * 6).map(|i| (i % 251) as u8).collect();
        let diffuse = SparseCubes::from_parts(c.min(), c.cell(), c.dims(), 4, 6, c.index().to_vec(), diffuse_data)
            .expect("diffuse");
        let points: Vec<[u32; 3]> = (0..40).map(|i| [i % 7, (i * 3) % 11, (i * 5) % 13]).collect();
        let (table, _) = PshTable::build(16, &points, &PshOptions::default()).expect("psh");
        let features = (0..table.slot_count() * 4).map(|i| i as f32 * 0.01).collect();
        Asset {
            meta: r#"{"scene":"test"}"#.into(),
            density,
            diffuse: Some(diffuse),
            psh: Some(PshEncoding { table, origin: Vec3::splat(-1.0), voxel: 0.125, feature_dim: 4, features }),
            tensors: vec![
                Tensor { name: "specular.0".into(), shape: vec![3, 2], data: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0] },
                Tensor { name: "specular.bias".into(), shape: vec![2], data: vec![0.5, -0.5] },
            ],
        }
    }

    fn sample_bytes() -> Vec<u8> {
        sample_asset().to_bytes().expect("encode")
    }

    /// Offset of section `kind`'s table entry.
    fn entry_of(bytes: &[u8], kind: SectionKind) -> usize {
        let count = le_u32(bytes, 12) as usize;
        (0..count).map(|i| HEADER_LEN + i * ENTRY_LEN).find(|&at| le_u32(bytes, at) == kind as u32).expect("section")
    }

    #[test]
    fn round_trip_through_a_file() {
        let asset = sample_asset();
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("a.nolf");
        asset.save(&path).expect("save");
        assert_eq!(Asset::load(&path).expect("load"), asset);
        let sizes = asset.sizes();
        assert_eq!(sizes.parts.len(), 6);
        assert!(sizes.total > 0);
    }

    #[test]
    fn truncated_files_are_rejected() {
        let bytes = sample_bytes();
        for len in [0, 4, 8, 20, 31, 32, 40, bytes.len() / 2, bytes.len() - 1] {
            match Asset::from_bytes(&bytes[..len]) {
                Err(AssetError::Truncated { available, .. }) => assert_eq!(available, len as u64),
                other => panic!("length {len}: {other:?}"),
            }
        }
    }

    #[test]
    fn corrupt_payload_fails_its_checksum() {
        let mut bytes = sample_bytes();
        let at = entry_of(&bytes, SectionKind::DensityCubes);
        let offset = le_u64(&bytes, at + 8) as usize;
        bytes[offset + 20] ^= 0x40;
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::SectionChecksum { section: "density cubes", .. })));
        let mut bytes = sample_bytes();
        bytes[HEADER_LEN + 17] ^= 1;
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::TableChecksum { .. })));
    }

    #[test]
    fn wrong_magic_and_version_are_rejected() {
        let mut bytes = sample_bytes();
        bytes[8..12].copy_from_slice(&2u32.to_le_bytes());
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::UnsupportedVersion { found: 2, supported: 1 })));
        let mut bytes = sample_bytes();
        bytes[0] = b'X';
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::NotAnAsset)));
        assert!(matches!(Asset::from_bytes(b"{\"json\": true}"), Err(AssetError::NotAnAsset)));
        let mut bytes = sample_bytes();
        bytes.push(0);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::LengthMismatch { .. })));
    }

    #[test]
    fn hostile_tables_are_rejected() {
        // Offsets past the end.
        let mut bytes = sample_bytes();
        let at = entry_of(&bytes, SectionKind::Tensors);
        let end = bytes.len() as u64;
        bytes[at + 8..at + 16].copy_from_slice(&end.to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(
            matches!(Asset::from_bytes(&bytes), Err(AssetError::SectionOutOfBounds { .. })),
            "{:?}",
            Asset::from_bytes(&bytes)
        );
        // Length that overflows.
        let mut bytes = sample_bytes();
        bytes[at + 16..at + 24].copy_from_slice(&u64::MAX.to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::SectionOutOfBounds { .. })));
        // A section over the header.
        let mut bytes = sample_bytes();
        bytes[at + 8..at + 16].copy_from_slice(&8u64.to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::SectionOutOfBounds { .. })));
        // Overlapping sections: point the tensors at the PSH section's bytes.
        let mut bytes = sample_bytes();
        let psh = entry_of(&bytes, SectionKind::Psh);
        let psh_offset = le_u64(&bytes, psh + 8);
        bytes[at + 8..at + 16].copy_from_slice(&(psh_offset + 8).to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::OverlappingSections { .. })));
        // Huge section count.
        let mut bytes = sample_bytes();
        bytes[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::TooLarge { what: "section count", .. })));
        // Duplicate and unknown kinds.
        let mut bytes = sample_bytes();
        bytes[at..at + 4].copy_from_slice(&(SectionKind::Psh as u32).to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::DuplicateSection(_))));
        bytes[at..at + 4].copy_from_slice(&99u32.to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::UnknownSection(99))));
        // Header claiming a huge length.
        let mut bytes = sample_bytes();
        bytes[16..24].copy_from_slice(&(1u64 << 40).to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::TooLarge { .. })));
    }

    #[test]
    fn hostile_counts_are_rejected_before_allocating() {
        // Huge grid dimensions inside a correctly checksummed density section.
        let mut bytes = sample_bytes();
        let offset = le_u64(&bytes, entry_of(&bytes, SectionKind::DensityCubes) + 8) as usize;
        for (field, value) in [(16, 1024u32), (20, 1024), (24, 1024)] {
            bytes[offset + field..offset + field + 4].copy_from_slice(&value.to_le_bytes());
        }
        reseal_checksums(&mut bytes);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::TooLarge { what: "cell count", .. })));
        // A cube count larger than the section holds.
        let mut bytes = sample_bytes();
        bytes[offset + 36..offset + 40].copy_from_slice(&200u32.to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(matches!(Asset::from_bytes(&bytes), Err(AssetError::Malformed { section: "density cubes", .. })));
        // A tensor claiming 2^26 elements in a few bytes.
        let mut bytes = sample_bytes();
        let offset = le_u64(&bytes, entry_of(&bytes, SectionKind::Tensors) + 8) as usize;
        let shape_at = offset + 4 + 4 + "specular.0".len() + 4;
        bytes[shape_at..shape_at + 4].copy_from_slice(&(1u32 << 25).to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(
            matches!(Asset::from_bytes(&bytes), Err(AssetError::Malformed { section: "tensors", .. })),
            "{:?}",
            Asset::from_bytes(&bytes)
        );
        // A PSH table whose key sits in the wrong slot.
        let mut bytes = sample_bytes();
        let offset = le_u64(&bytes, entry_of(&bytes, SectionKind::Psh) + 8) as usize;
        let (m, r) = (le_u32(&bytes, offset + 4) as usize, le_u32(&bytes, offset + 8) as usize);
        let keys_at = offset + 32 + 6 * r * r * r;
        let first_full = (0..m * m * m).find(|&s| le_u32(&bytes, keys_at + 4 * s) != u32::MAX).expect("a key");
        let other = (first_full + 1) % (m * m * m);
        let (a, b) = (keys_at + 4 * first_full, keys_at + 4 * other);
        let ka: [u8; 4] = bytes[a..a + 4].try_into().expect("4");
        let kb: [u8; 4] = bytes[b..b + 4].try_into().expect("4");
        bytes[a..a + 4].copy_from_slice(&kb);
        bytes[b..b + 4].copy_from_slice(&ka);
        reseal_checksums(&mut bytes);
        assert!(matches!(
            Asset::from_bytes(&bytes),
            Err(AssetError::Malformed { section: "perfect spatial hash", .. })
        ));
    }

    #[test]
    fn missing_density_is_an_error() {
        // Keep only the first table entry (the meta section).
        let mut bytes = sample_bytes();
        bytes[12..16].copy_from_slice(&1u32.to_le_bytes());
        reseal_checksums(&mut bytes);
        assert!(
            matches!(Asset::from_bytes(&bytes), Err(AssetError::MissingSection("density cubes"))),
            "{:?}",
            Asset::from_bytes(&bytes)
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(400))]

        /// Random byte flips, truncations and insertions never panic, with or without the
        /// checksums repaired (repairing them lets the mutations reach the section parsers).
        #[test]
        fn random_mutations_never_panic(
            edits in proptest::collection::vec((any::<proptest::sample::Index>(), any::<u8>(), 0u8..4), 1..8),
            reseal in any::<bool>(),
        ) {
            let mut bytes = sample_bytes();
            for (at, value, op) in edits {
                if bytes.is_empty() { break; }
                let i = at.index(bytes.len());
                match op {
                    0 | 1 => bytes[i] = value,
                    2 => bytes.truncate(i),
                    _ => bytes.insert(i, value),
                }
            }
            if reseal {
                reseal_checksums(&mut bytes);
            }
            let _ = Asset::from_bytes(&bytes);
        }
    }
}
