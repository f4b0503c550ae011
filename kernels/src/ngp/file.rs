//! The file of a trained radiance field.
//!
//! Layout (little-endian):
//!
//! | bytes | content |
//! | --- | --- |
//! | 8 | magic `NEPHNGP\0` |
//! | 4 | version (1) |
//! | 4 x 12 | hash levels, log2 table size, base resolution, per-level scale (f32 bits), density hidden width, geometric features, colour hidden width, colour hidden layers, SH degree, steps per diagonal, occupancy resolution, reserved (0) |
//! | 4 x 4 | box min x, y, z, side (f32) |
//! | 8 x 4 | counts: hash-grid values, density-MLP values, colour-MLP values, occupancy words |
//! | ... | hash grid, density MLP, colour MLP (f32), occupancy bits (u64) |
//! | 8 | FNV-1a 64 checksum of every byte before it |
//!
//! Loading checks the magic, the version, every configuration value, that each count
//! matches what the configuration implies and that the file is exactly as long as the
//! header says, all before allocating anything for the payload; then the checksum, then the
//! values (every parameter must be finite).

use std::io::{Read, Write};
use std::path::Path;

use glam::Vec3;

use nephele_nn::{HashGrid, HashGridConfig, Mlp};

use super::NgpError;
use super::field::{FieldConfig, RadianceField};
use super::occupancy::OccupancyGrid;

/// First bytes of a radiance field file.
pub const MAGIC: [u8; 8] = *b"NEPHNGP\0";
/// Current format version.
pub const VERSION: u32 = 1;
const HEADER_LEN: usize = 8 + 4 + 12 * 4 + 4 * 4 + 4 * 8;
/// Largest payload accepted (2 GiB): a hostile header cannot make the loader reserve more.
const MAX_PAYLOAD: u64 = 1 << 31;

/// FNV-1a, 64 bits.
fn fnv1a(hash: u64, bytes: &[u8]) -> u64 {
    let mut h = hash;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01B3);
    }
    h
}
const FNV_OFFSET: u64 = 0xCBF2_9CE4_8422_2325;

fn io(path: &Path) -> impl Fn(std::io::Error) -> NgpError + '_ {
    move |source| NgpError::Io { path: path.to_path_buf(), source }
}

/// Serialises a field to bytes.
pub fn to_bytes(field: &RadianceField) -> Vec<u8> {
    let c = &field.config;
    let mut out = Vec::with_capacity(HEADER_LEN + 4 * field.num_params() + 8 * field.occupancy.words().len() + 8);
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    let header = [
        c.grid.levels,
        c.grid.log2_table_size,
        c.grid.base_resolution,
        c.grid.per_level_scale.to_bits(),
        c.density_hidden as u32,
        c.geo_features as u32,
        c.color_hidden as u32,
        c.color_hidden_layers as u32,
        c.sh_degree,
        c.steps_per_diagonal,
        c.occupancy_resolution,
        0,
    ];
    for v in header {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for v in [field.min.x, field.min.y, field.min.z, field.size] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for n in
        [field.grid.num_params(), field.density.num_params(), field.color.num_params(), field.occupancy.words().len()]
    {
        out.extend_from_slice(&(n as u64).to_le_bytes());
    }
    for p in [field.grid.params(), field.density.params(), field.color.params()] {
        for v in p {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    for w in field.occupancy.words() {
        out.extend_from_slice(&w.to_le_bytes());
    }
    let sum = fnv1a(FNV_OFFSET, &out);
    out.extend_from_slice(&sum.to_le_bytes());
    out
}

/// Writes a field to `path` (via a temporary file renamed into place).
pub fn save_field(field: &RadianceField, path: &Path) -> Result<(), NgpError> {
    let bytes = to_bytes(field);
    let tmp = path.with_extension("partial");
    let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
    f.write_all(&bytes).map_err(io(&tmp))?;
    f.sync_all().map_err(io(&tmp))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io(path))
}

/// Parsed and validated header.
#[derive(Debug)]
struct Header {
    config: FieldConfig,
    min: Vec3,
    size: f32,
    counts: [u64; 4],
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

fn parse_header(b: &[u8]) -> Result<Header, String> {
    if b.len() < HEADER_LEN {
        return Err(format!("{} bytes is shorter than the {HEADER_LEN}-byte header", b.len()));
    }
    if b[..8] != MAGIC {
        return Err("bad magic (not a Nephele radiance field)".into());
    }
    let version = u32_at(b, 8);
    if version != VERSION {
        return Err(format!("unsupported version {version} (this build reads {VERSION})"));
    }
    let h: Vec<u32> = (0..12).map(|k| u32_at(b, 12 + 4 * k)).collect();
    let config = FieldConfig {
        grid: HashGridConfig {
            levels: h[0],
            log2_table_size: h[1],
            base_resolution: h[2],
            per_level_scale: f32::from_bits(h[3]),
        },
        density_hidden: h[4] as usize,
        geo_features: h[5] as usize,
        color_hidden: h[6] as usize,
        color_hidden_layers: h[7] as usize,
        sh_degree: h[8],
        steps_per_diagonal: h[9],
        occupancy_resolution: h[10],
    };
    config.validate().map_err(|e| e.to_string())?;
    let f = |k: usize| f32::from_bits(u32_at(b, 60 + 4 * k));
    let (min, size) = (Vec3::new(f(0), f(1), f(2)), f(3));
    if !(min.is_finite() && size.is_finite() && size > 0.0) {
        return Err(format!("bad box: min {min}, side {size}"));
    }
    let mut counts = [0u64; 4];
    for (k, c) in counts.iter_mut().enumerate() {
        let i = 76 + 8 * k;
        *c = u64::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3], b[i + 4], b[i + 5], b[i + 6], b[i + 7]]);
    }
    let expected = [
        config.grid.num_params() as u64,
        config.density_config().num_params() as u64,
        config.color_config().num_params() as u64,
        OccupancyGrid::word_count(config.occupancy_resolution) as u64,
    ];
    if counts != expected {
        return Err(format!("stored sizes {counts:?} do not match the configuration's {expected:?}"));
    }
    Ok(Header { config, min, size, counts })
}

/// Reads a field from bytes (see the module documentation for what is checked).
pub fn from_bytes(bytes: &[u8]) -> Result<RadianceField, String> {
    let header = parse_header(bytes)?;
    let payload = 4 * (header.counts[0] + header.counts[1] + header.counts[2]) + 8 * header.counts[3];
    if payload > MAX_PAYLOAD {
        return Err(format!("payload of {payload} bytes exceeds the {MAX_PAYLOAD}-byte limit"));
    }
    let total = HEADER_LEN as u64 + payload + 8;
    if bytes.len() as u64 != total {
        return Err(format!("file is {} bytes, the header implies {total} (truncated or padded)", bytes.len()));
    }
    let body = &bytes[..bytes.len() - 8];
    let tail = &bytes[bytes.len() - 8..];
    let stored = u64::from_le_bytes([tail[0], tail[1], tail[2], tail[3], tail[4], tail[5], tail[6], tail[7]]);
    if fnv1a(FNV_OFFSET, body) != stored {
        return Err("checksum mismatch (corrupt file)".into());
    }
    let mut at = HEADER_LEN;
    let mut floats = |n: u64| -> Result<Vec<f32>, String> {
        let n = n as usize;
        let v: Vec<f32> =
            body[at..at + 4 * n].chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        at += 4 * n;
        if v.iter().all(|x| x.is_finite()) { Ok(v) } else { Err("non-finite parameter".into()) }
    };
    let c = header.config;
    let mut grid = HashGrid::zeros(c.grid).map_err(|e| e.to_string())?;
    grid.params_mut().copy_from_slice(&floats(header.counts[0])?);
    let mut density = Mlp::zeros(c.density_config()).map_err(|e| e.to_string())?;
    density.params_mut().copy_from_slice(&floats(header.counts[1])?);
    let mut color = Mlp::zeros(c.color_config()).map_err(|e| e.to_string())?;
    color.params_mut().copy_from_slice(&floats(header.counts[2])?);
    let words: Vec<u64> = body[at..]
        .chunks_exact(8)
        .map(|w| u64::from_le_bytes([w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7]]))
        .collect();
    let occupancy = OccupancyGrid::from_words(c.occupancy_resolution, words).ok_or("bad occupancy grid")?;
    Ok(RadianceField { config: c, min: header.min, size: header.size, grid, density, color, occupancy })
}

/// Loads a field from `path`, checking the header against the file's length before reading
/// the payload.
pub fn load_field(path: &Path) -> Result<RadianceField, NgpError> {
    let format = |reason: String| NgpError::Format { path: path.to_path_buf(), reason };
    let mut file = std::fs::File::open(path).map_err(io(path))?;
    let len = file.metadata().map_err(io(path))?.len();
    let mut head = vec![0u8; HEADER_LEN.min(len as usize)];
    file.read_exact(&mut head).map_err(io(path))?;
    let header = parse_header(&head).map_err(format)?;
    let payload = 4 * (header.counts[0] + header.counts[1] + header.counts[2]) + 8 * header.counts[3];
    let total = HEADER_LEN as u64 + payload + 8;
    if payload > MAX_PAYLOAD || len != total {
        return Err(format(format!("file is {len} bytes, the header implies {total} (truncated or padded)")));
    }
    let mut bytes = head;
    bytes.reserve_exact((total - HEADER_LEN as u64) as usize);
    file.read_to_end(&mut bytes).map_err(io(path))?;
    from_bytes(&bytes).map_err(format)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny_field() -> RadianceField {
        let config = FieldConfig::small_test();
        RadianceField::new(config, Vec3::new(-1.0, -1.0, -0.5), 2.0, 3).expect("field")
    }

    #[test]
    fn round_trip_and_rejections() {
        let mut field = tiny_field();
        let mut occ = field.occupancy().clone();
        occ.set(5, false);
        occ.rebuild_coarse();
        field.set_occupancy(occ).expect("occupancy");
        let bytes = to_bytes(&field);
        let back = from_bytes(&bytes).expect("round trip");
        assert_eq!(back.grid, field.grid);
        assert_eq!(back.density, field.density);
        assert_eq!(back.color, field.color);
        assert_eq!(back.occupancy, field.occupancy);
        assert_eq!((back.min, back.size, back.config), (field.min, field.size, field.config));

        // Truncated anywhere, flipped bits, bad magic or version: clear errors, no panic.
        for cut in [0, 7, 20, HEADER_LEN - 1, HEADER_LEN, bytes.len() / 2, bytes.len() - 1] {
            assert!(from_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut corrupt = bytes.clone();
        corrupt[HEADER_LEN + 10] ^= 0x40;
        assert!(from_bytes(&corrupt).expect_err("corrupt").contains("checksum"));
        let mut magic = bytes.clone();
        magic[0] = b'X';
        assert!(from_bytes(&magic).expect_err("magic").contains("magic"));
        let mut version = bytes.clone();
        version[8] = 9;
        assert!(from_bytes(&version).expect_err("version").contains("version"));
        // A hostile header asking for a huge table is refused before any allocation.
        let mut hostile = bytes.clone();
        hostile[16..20].copy_from_slice(&26u32.to_le_bytes());
        hostile[12..16].copy_from_slice(&32u32.to_le_bytes());
        assert!(from_bytes(&hostile).is_err());
        let mut counts = bytes.clone();
        counts[76..84].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(from_bytes(&counts).expect_err("counts").contains("sizes"));
        let mut padded = bytes.clone();
        padded.push(0);
        assert!(from_bytes(&padded).is_err());
    }

    #[test]
    fn save_and_load_through_a_file() {
        let field = tiny_field();
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("field.ngp");
        save_field(&field, &path).expect("save");
        let back = load_field(&path).expect("load");
        assert_eq!(back.grid, field.grid);
        let bytes = to_bytes(&field);
        std::fs::write(&path, &bytes[..bytes.len() / 2]).expect("write");
        let err = load_field(&path).expect_err("truncated");
        assert!(err.to_string().contains("truncated"), "{err}");
        std::fs::write(&path, b"short").expect("write");
        assert!(load_field(&path).is_err());
        assert!(load_field(&dir.path().join("missing")).is_err());
    }
}
