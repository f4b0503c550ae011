//! Training checkpoints that a later run resumes bit for bit: a run's state (a JSON header:
//! its options, step, loss curve, random stream), the network's parameters and Adam's two
//! moments, with a CRC-32, written to a temporary file and renamed into place so that a
//! crash never leaves half a checkpoint. Every trainer with checkpoints (the GI U-Net, the
//! NeLF) uses this one format, each under its own magic.

use std::path::{Path, PathBuf};

use serde::Serialize;
use serde::de::DeserializeOwned;
use thiserror::Error;

/// A trainer's state, and the magic and version of its checkpoint files.
pub trait CheckpointState: Serialize + DeserializeOwned {
    /// Four bytes that tell this trainer's checkpoints from others'.
    const MAGIC: &'static [u8; 4];
    const VERSION: u32;
    /// What the file is, for errors ("GI training checkpoint").
    const WHAT: &'static str;
}

#[derive(Debug, Error)]
#[error("checkpoint {path}: {reason}")]
pub struct CheckpointError {
    pub path: PathBuf,
    pub reason: String,
}

/// A run's weights, optimiser moments and state.
#[derive(Debug, Clone)]
pub struct Checkpoint<S> {
    pub state: S,
    pub params: Vec<f32>,
    pub m: Vec<f32>,
    pub v: Vec<f32>,
}

impl<S: CheckpointState> Checkpoint<S> {
    pub fn save(&self, path: &Path) -> Result<(), CheckpointError> {
        let err = |reason: String| CheckpointError { path: path.to_path_buf(), reason };
        if self.m.len() != self.params.len() || self.v.len() != self.params.len() {
            return Err(err("moments and parameters differ in length".into()));
        }
        let header = serde_json::to_vec(&self.state).map_err(|e| err(e.to_string()))?;
        let mut out = Vec::with_capacity(16 + header.len() + 12 * self.params.len() + 4);
        out.extend_from_slice(S::MAGIC);
        out.extend_from_slice(&S::VERSION.to_le_bytes());
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(&(self.params.len() as u32).to_le_bytes());
        out.extend_from_slice(&header);
        for v in self.params.iter().chain(&self.m).chain(&self.v) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        let tmp = path.with_extension("part");
        std::fs::write(&tmp, &out).map_err(|e| err(e.to_string()))?;
        std::fs::rename(&tmp, path).map_err(|e| err(e.to_string()))
    }

    pub fn load(path: &Path) -> Result<Checkpoint<S>, CheckpointError> {
        let err = |reason: String| CheckpointError { path: path.to_path_buf(), reason };
        let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
        if bytes.len() < 20 || &bytes[..4] != S::MAGIC {
            return Err(err(format!("not a {}", S::WHAT)));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(body).to_le_bytes() != crc {
            return Err(err("checksum mismatch: damaged or truncated".into()));
        }
        let word = |at: usize| u32::from_le_bytes([body[at], body[at + 1], body[at + 2], body[at + 3]]) as usize;
        if word(4) != S::VERSION as usize {
            return Err(err(format!("version {}", word(4))));
        }
        let (header_len, n) = (word(8), word(12));
        let header_end = 16 + header_len;
        if body.len() != header_end.saturating_add(n.saturating_mul(12)) {
            return Err(err("lengths do not add up".into()));
        }
        let state: S = serde_json::from_slice(&body[16..header_end]).map_err(|e| err(e.to_string()))?;
        let floats: Vec<f32> =
            body[header_end..].chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let (params, rest) = floats.split_at(n);
        let (m, v) = rest.split_at(n);
        Ok(Checkpoint { state, params: params.to_vec(), m: m.to_vec(), v: v.to_vec() })
    }
}
