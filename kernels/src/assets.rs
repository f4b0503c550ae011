//! The one registry of asset formats: which file becomes which kernel.
//!
//! The worker (assets named by id, `<id>.<extension>` in its asset folder) and
//! `nephele render` (a file given on the command line, recognised by its first bytes) both
//! open assets through [`FORMATS`], so a new kernel family (the GPU backend, NeLF, stereo
//! GI) is added here once.

use std::io::Read;
use std::path::Path;
use std::sync::Arc;

use thiserror::Error;

use crate::inolf::kernel::InolfKernel;
use crate::kernel::{PathTracedKernel, RayKernel};
use crate::nelf::NelfKernel;
use crate::ngp::NgpKernel;
use nephele_nn::SimdMode;

/// A device that takes kernels over once the CPU has loaded them: the GPU backend
/// (`nephele-gpu`) implements it, so that this registry stays the one place that turns files
/// into kernels without depending on a GPU API.
pub trait Accelerator: Send + Sync + std::fmt::Debug {
    /// The device's twin of an i-NOLF kernel, or why it cannot have one.
    fn inolf(&self, kernel: &InolfKernel) -> Result<Arc<dyn RayKernel>, String>;
    /// The device's twin of the i-NGP-style baseline.
    fn ngp(&self, kernel: &NgpKernel) -> Result<Arc<dyn RayKernel>, String>;
    /// A GI model's U-Net resident on the device (the G-buffer stays on the CPU).
    fn unet(&self, network: &nephele_nn::UNet) -> Result<Arc<dyn crate::gi::UNetDevice>, String>;
    /// The device, for logs and reports.
    fn label(&self) -> String;
}

/// Knobs chosen at load time: the cost of path-traced assets, the instruction set of the
/// neural kernels, the device that runs them.
#[derive(Debug, Clone)]
pub struct LoadOptions {
    /// Samples per pixel of path-traced assets (built-in scenes, glTF).
    pub pathtrace_spp: u32,
    /// Bounces of path-traced assets.
    pub pathtrace_bounces: u32,
    /// Instruction set of the i-NOLF and i-NGP kernels (`--simd`).
    pub simd: SimdMode,
    /// Where kernels with a GPU twin run (`--device`); `None`: the CPU.
    pub accelerator: Option<Arc<dyn Accelerator>>,
    /// Voxels between the i-NOLF march's samples (`--march-stride`; 1: every voxel); `None`:
    /// the stride each asset's bake chose ([`crate::inolf::heads::InolfMeta::march_stride`]).
    /// The speed-for-error knob of the march, on the CPU and on the GPU twin alike.
    pub march_stride: Option<u32>,
}

impl Default for LoadOptions {
    fn default() -> LoadOptions {
        LoadOptions {
            pathtrace_spp: 4,
            pathtrace_bounces: 4,
            simd: SimdMode::Auto,
            accelerator: None,
            march_stride: None,
        }
    }
}

/// Why an asset file did not become a kernel.
#[derive(Debug, Error)]
pub enum LoadError {
    #[error("reading {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path} is not a known asset format (first bytes {magic:?}; known: {known})")]
    UnknownFormat { path: String, magic: String, known: String },
    #[error("{0}")]
    Invalid(String),
}

/// One asset format: its file extension, the kernel kind it yields and how to load it.
#[derive(Debug, Clone, Copy)]
pub struct AssetFormat {
    /// File extension, lower case, without the dot.
    pub extension: &'static str,
    /// The kernel kind it produces ([`RayKernel::kind`]).
    pub kernel_kind: &'static str,
    /// The file's first eight bytes, where the format has a magic number.
    pub magic: Option<[u8; 8]>,
    /// Opens a file of this format.
    pub load: LoadFn,
}

/// How a format opens a file.
pub type LoadFn = fn(&Path, &LoadOptions) -> Result<Arc<dyn RayKernel>, LoadError>;

/// Every format this build can load.
pub const FORMATS: &[AssetFormat] = &[
    AssetFormat { extension: "nolf", kernel_kind: "inolf", magic: Some(crate::inolf::asset::MAGIC), load: load_inolf },
    AssetFormat { extension: "ngp", kernel_kind: "ngp", magic: Some(crate::ngp::FILE_MAGIC), load: load_ngp },
    AssetFormat { extension: "nelf", kernel_kind: "nelf", magic: Some(crate::nelf::NELF_MAGIC), load: load_nelf },
    AssetFormat { extension: "ngi", kernel_kind: "gi", magic: Some(GI_MAGIC8), load: load_gi },
    AssetFormat { extension: "glb", kernel_kind: "pathtrace", magic: None, load: load_gltf },
    AssetFormat { extension: "gltf", kernel_kind: "pathtrace", magic: None, load: load_gltf },
];

fn load_inolf(path: &Path, options: &LoadOptions) -> Result<Arc<dyn RayKernel>, LoadError> {
    let mut kernel = InolfKernel::load(path).map_err(|e| LoadError::Invalid(e.to_string()))?;
    kernel.set_simd(options.simd);
    if let Some(stride) = options.march_stride {
        kernel.set_march_stride(stride).map_err(|e| LoadError::Invalid(e.to_string()))?;
    }
    match &options.accelerator {
        // The twin marches at the kernel's stride.
        Some(device) => device.inolf(&kernel).map_err(LoadError::Invalid),
        None => Ok(Arc::new(kernel)),
    }
}

fn load_ngp(path: &Path, options: &LoadOptions) -> Result<Arc<dyn RayKernel>, LoadError> {
    let mut kernel = NgpKernel::load(path).map_err(|e| LoadError::Invalid(e.to_string()))?;
    kernel.set_simd(options.simd);
    match &options.accelerator {
        Some(device) => device.ngp(&kernel).map_err(LoadError::Invalid),
        None => Ok(Arc::new(kernel)),
    }
}

/// NeLF assets run on the CPU: there is no GPU twin yet, so with a device chosen they stay
/// on the CPU (logged).
fn load_nelf(path: &Path, options: &LoadOptions) -> Result<Arc<dyn RayKernel>, LoadError> {
    let mut kernel = NelfKernel::load(path).map_err(|e| LoadError::Invalid(e.to_string()))?;
    kernel.set_simd(options.simd);
    if let Some(device) = &options.accelerator {
        tracing::warn!(asset = %path.display(), device = %device.label(), "NeLF has no GPU kernel yet: it runs on the CPU");
    }
    Ok(Arc::new(kernel))
}

/// The first eight bytes of a `.ngi` file: magic and format version.
const GI_MAGIC8: [u8; 8] = {
    let v = crate::gi::GI_FORMAT_VERSION.to_le_bytes();
    let m = crate::gi::GI_MAGIC;
    [m[0], m[1], m[2], m[3], v[0], v[1], v[2], v[3]]
};

/// An environment's GI model (and its `.stereo.ngi` twin beside it); with an accelerator its
/// networks run there (the G-buffer is path traced on the CPU either way).
fn load_gi(path: &Path, options: &LoadOptions) -> Result<Arc<dyn RayKernel>, LoadError> {
    let settings = crate::environment::GiServeSettings::default();
    let mut kernel =
        crate::environment::GiKernel::load(path, settings).map_err(|e| LoadError::Invalid(e.to_string()))?;
    kernel.set_simd(options.simd);
    let Some(accelerator) = &options.accelerator else {
        return Ok(Arc::new(kernel));
    };
    let (single, stereo) = kernel.models();
    let single_net = accelerator.unet(&single.network).map_err(LoadError::Invalid)?;
    let stereo_net = stereo.map(|s| accelerator.unet(&s.network)).transpose().map_err(LoadError::Invalid)?;
    let devices = crate::environment::GiDevices { single: single_net, stereo: stereo_net };
    let kernel = kernel.with_devices(devices).map_err(|e| LoadError::Invalid(e.to_string()))?;
    tracing::info!(asset = %path.display(), device = %kernel.network_device(), "GI networks resident on the device");
    Ok(Arc::new(kernel))
}

fn load_gltf(path: &Path, options: &LoadOptions) -> Result<Arc<dyn RayKernel>, LoadError> {
    let scene = nephele_pathtracer::gltf_import::import_gltf(path).map_err(|e| LoadError::Invalid(e.to_string()))?;
    path_traced(scene, options)
}

/// The reference path tracer over `scene` as a kernel.
pub fn path_traced(scene: nephele_pathtracer::Scene, options: &LoadOptions) -> Result<Arc<dyn RayKernel>, LoadError> {
    let invalid = |e: &dyn std::fmt::Display| LoadError::Invalid(e.to_string());
    let renderer = nephele_pathtracer::Renderer::new(scene).map_err(|e| invalid(&e))?;
    let kernel =
        PathTracedKernel::new(renderer, options.pathtrace_spp, options.pathtrace_bounces).map_err(|e| invalid(&e))?;
    Ok(Arc::new(kernel))
}

/// Opens an asset file whose format has a magic number, recognised by its first bytes
/// whatever its name.
pub fn load_by_magic(path: &Path, options: &LoadOptions) -> Result<Arc<dyn RayKernel>, LoadError> {
    let mut magic = [0u8; 8];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .map_err(|source| LoadError::Io { path: path.display().to_string(), source })?;
    match FORMATS.iter().find(|f| f.magic == Some(magic)) {
        Some(format) => (format.load)(path, options),
        None => Err(LoadError::UnknownFormat {
            path: path.display().to_string(),
            magic: String::from_utf8_lossy(&magic).into_owned(),
            known: FORMATS
                .iter()
                .filter(|f| f.magic.is_some())
                .map(|f| format!(".{}", f.extension))
                .collect::<Vec<_>>()
                .join(", "),
        }),
    }
}

/// Recomputes the trailing CRC-32 of a `.nelf` or `.ngi` file (the checksum over every byte
/// before it), so that tests and fuzzers reach the parsers with mutated bytes instead of
/// stopping at the checksum. `false` when the input is too short to hold one.
pub fn reseal_trailing_crc(bytes: &mut [u8]) -> bool {
    let Some(end) = bytes.len().checked_sub(4) else {
        return false;
    };
    let crc = crc32fast::hash(&bytes[..end]);
    bytes[end..].copy_from_slice(&crc.to_le_bytes());
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extensions_are_unique_and_magic_numbers_distinct() {
        for (i, a) in FORMATS.iter().enumerate() {
            for b in &FORMATS[i + 1..] {
                assert_ne!(a.extension, b.extension);
                if a.magic.is_some() {
                    assert_ne!(a.magic, b.magic);
                }
            }
        }
    }

    /// A device that has no twins.
    #[derive(Debug)]
    struct NoTwins;

    impl Accelerator for NoTwins {
        fn inolf(&self, kernel: &InolfKernel) -> Result<Arc<dyn RayKernel>, String> {
            Err(format!("no i-NOLF twin at stride {}", kernel.density().march_stride()))
        }
        fn ngp(&self, _: &NgpKernel) -> Result<Arc<dyn RayKernel>, String> {
            Err("no i-NGP twin".into())
        }
        fn unet(&self, _: &nephele_nn::UNet) -> Result<Arc<dyn crate::gi::UNetDevice>, String> {
            Err("no U-Net".into())
        }
        fn label(&self) -> String {
            "none".into()
        }
    }

    #[test]
    fn the_device_twin_is_asked_for_at_the_kernels_march_stride() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("object.nolf");
        let object = crate::inolf::synthetic::synthetic_object(1.0).expect("object");
        let mut asset = object.asset().expect("asset");
        asset.save(&path).expect("save");
        // The stride the device twin is handed, for a stride asked (or none).
        let twin_is_asked_at = |asked: Option<u32>, marched: u32| {
            let options =
                LoadOptions { accelerator: Some(Arc::new(NoTwins)), march_stride: asked, ..LoadOptions::default() };
            let refused = load_inolf(&path, &options).expect_err("no twin");
            assert!(refused.to_string().contains(&format!("no i-NOLF twin at stride {marched}")), "{refused}");
        };
        twin_is_asked_at(None, 1);
        twin_is_asked_at(Some(3), 3);
        let bad = LoadOptions { march_stride: Some(0), ..LoadOptions::default() };
        assert!(load_inolf(&path, &bad).is_err());
        // The bake's choice travels in the asset; the renderer's option still overrides it.
        crate::inolf::heads::set_asset_march_stride(&mut asset, 2).expect("stride 2");
        assert!(crate::inolf::heads::set_asset_march_stride(&mut asset, 0).is_err());
        asset.save(&path).expect("save");
        twin_is_asked_at(None, 2);
        twin_is_asked_at(Some(1), 1);
        let cpu = load_inolf(&path, &LoadOptions::default()).expect("the CPU kernel");
        assert_eq!(cpu.kind(), "inolf");
    }

    #[test]
    fn unknown_and_short_files_are_clear_errors() {
        let dir = tempfile::tempdir().expect("tempdir");
        let unknown = dir.path().join("x.bin");
        std::fs::write(&unknown, b"NOTANASSET").expect("write");
        let err = load_by_magic(&unknown, &LoadOptions::default()).expect_err("unknown");
        assert!(matches!(err, LoadError::UnknownFormat { .. }), "{err}");
        assert!(err.to_string().contains(".nolf"), "{err}");
        let short = dir.path().join("short.nolf");
        std::fs::write(&short, b"NO").expect("write");
        assert!(matches!(load_by_magic(&short, &LoadOptions::default()), Err(LoadError::Io { .. })));
        let corrupt = dir.path().join("corrupt.ngp");
        let mut bytes = crate::ngp::FILE_MAGIC.to_vec();
        bytes.extend_from_slice(b"garbage");
        std::fs::write(&corrupt, bytes).expect("write");
        assert!(matches!(load_by_magic(&corrupt, &LoadOptions::default()), Err(LoadError::Invalid(_))));
    }
}
