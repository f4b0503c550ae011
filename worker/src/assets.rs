//! Assets on demand: an asset id from a [`nephele_proto::RayBatch`] becomes a kernel.
//!
//! [`DirAssetLoader`] resolves an id in this order:
//! 1. a file `<dir>/<id>.<ext>` for a format of the kernels' registry
//!    ([`nephele_kernels::assets::FORMATS`]: `.nolf` i-NOLF, `.ngp` the i-NGP-style
//!    baseline, `.glb` / `.gltf` path-traced) or one added with
//!    [`DirAssetLoader::register_format`];
//! 2. a built-in scene (`nephele_pathtracer::scenes::builtin`), rendered by the path tracer at
//!    low samples per pixel;
//! 3. otherwise [`AssetError::Unknown`].
//!
//! Ids are validated first (`[A-Za-z0-9._-]`, no leading dot, no `..`) and the resolved
//! file must canonicalise to a path inside the asset directory, so no id (and no symlink
//! planted in the directory) reaches a file outside it.

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use nephele_kernels::assets::{self, LoadOptions};
use nephele_kernels::kernel::RayKernel;
use nephele_pathtracer::scenes;
use nephele_proto::{ErrorCode, ValidationError, validate};
use thiserror::Error;

/// A kernel ready to render batches.
pub type Kernel = Arc<dyn RayKernel>;

/// Turns asset ids into kernels. Implementations cache; `load` may block (file I/O, BVH
/// builds), so callers run it on a blocking thread.
pub trait AssetLoader: Send + Sync + fmt::Debug {
    /// The kernel kinds this loader can produce, for registration with the master.
    fn kernel_kinds(&self) -> Vec<String>;

    /// The kernel for `asset_id`.
    fn load(&self, asset_id: &str) -> Result<Kernel, AssetError>;
}

#[derive(Debug, Error)]
pub enum AssetError {
    #[error(transparent)]
    InvalidId(#[from] ValidationError),
    #[error("unknown asset '{id}': no built-in scene of that name and no {id}.<{extensions}> in {dir}")]
    Unknown { id: String, dir: PathBuf, extensions: String },
    #[error("asset '{id}' resolves outside the asset directory")]
    Escapes { id: String },
    #[error("asset file {path}: the '{extension}' format is not supported by this worker yet")]
    Unsupported { path: PathBuf, extension: String },
    #[error("loading asset '{id}': {reason}")]
    Load { id: String, reason: String },
}

impl AssetError {
    /// The code a worker reports in `BatchFailed`.
    pub fn code(&self) -> ErrorCode {
        match self {
            AssetError::InvalidId(_) | AssetError::Escapes { .. } => ErrorCode::InvalidField,
            AssetError::Unknown { .. } => ErrorCode::UnknownAsset,
            AssetError::Unsupported { .. } | AssetError::Load { .. } => ErrorCode::AssetLoadFailed,
        }
    }
}

/// Knobs for the kernels a loader builds.
#[derive(Debug, Clone)]
pub struct AssetOptions {
    /// What the kernels' registry needs to open an asset (path-traced samples and bounces).
    pub load: LoadOptions,
    /// Most kernels kept loaded; the oldest is dropped beyond that.
    pub max_cached: usize,
}

impl Default for AssetOptions {
    fn default() -> AssetOptions {
        AssetOptions { load: LoadOptions::default(), max_cached: 32 }
    }
}

/// Builds a kernel from a file of one format. Register one per extension with
/// [`DirAssetLoader::register_format`]: this is where the neural formats plug in.
pub type FormatHandler = Arc<dyn Fn(&Path, &AssetOptions) -> Result<Kernel, String> + Send + Sync>;

/// Extensions known to the project whose kernels are not in this build: a file with one of
/// them is a clear "not supported yet" error rather than "unknown asset".
pub const PENDING_FORMATS: &[&str] = &[];

type Slot = Arc<Mutex<Option<Kernel>>>;

/// Loads assets from a directory and the built-in scenes; see the module documentation.
pub struct DirAssetLoader {
    dir: PathBuf,
    options: AssetOptions,
    formats: Vec<(String, &'static str, FormatHandler)>,
    /// Per-id slots (so that two batches of one new asset load it once) and load order.
    cache: Mutex<(HashMap<String, Slot>, Vec<String>)>,
}

impl fmt::Debug for DirAssetLoader {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("DirAssetLoader")
            .field("dir", &self.dir)
            .field("options", &self.options)
            .field("formats", &self.formats.iter().map(|(ext, kind, _)| (ext, kind)).collect::<Vec<_>>())
            .finish_non_exhaustive()
    }
}

impl DirAssetLoader {
    /// A loader for `dir` (which must exist) with every format of the kernels' registry.
    pub fn new(dir: &Path, options: AssetOptions) -> std::io::Result<DirAssetLoader> {
        let dir = dir.canonicalize()?;
        if !dir.is_dir() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::NotADirectory,
                format!("{} is not a directory", dir.display()),
            ));
        }
        let mut loader =
            DirAssetLoader { dir, options, formats: Vec::new(), cache: Mutex::new((HashMap::new(), Vec::new())) };
        for format in assets::FORMATS {
            let load = format.load;
            let handler: FormatHandler =
                Arc::new(move |path, options| load(path, &options.load).map_err(|e| e.to_string()));
            loader.register_format(format.extension, format.kernel_kind, handler);
        }
        Ok(loader)
    }

    /// Adds (or replaces) the handler for files `<id>.<extension>`, producing kernels of
    /// kind `kernel_kind`.
    pub fn register_format(&mut self, extension: &str, kernel_kind: &'static str, handler: FormatHandler) {
        let extension = extension.to_ascii_lowercase();
        self.formats.retain(|(ext, _, _)| *ext != extension);
        self.formats.push((extension, kernel_kind, handler));
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn load_uncached(&self, id: &str) -> Result<Kernel, AssetError> {
        let extensions = self.formats.iter().map(|(ext, _, _)| ext.as_str()).chain(PENDING_FORMATS.iter().copied());
        for ext in extensions {
            let candidate = self.dir.join(format!("{id}.{ext}"));
            if !candidate.exists() {
                continue;
            }
            let path =
                candidate.canonicalize().map_err(|e| AssetError::Load { id: id.into(), reason: e.to_string() })?;
            if !path.starts_with(&self.dir) || !path.is_file() {
                return Err(AssetError::Escapes { id: id.into() });
            }
            let Some((_, _, handler)) = self.formats.iter().find(|(e, _, _)| e == ext) else {
                return Err(AssetError::Unsupported { path, extension: ext.into() });
            };
            tracing::info!(asset = id, path = %path.display(), "loading asset file");
            return handler(&path, &self.options).map_err(|reason| AssetError::Load { id: id.into(), reason });
        }
        if scenes::names().contains(&id) {
            tracing::info!(asset = id, spp = self.options.load.pathtrace_spp, "loading built-in scene (path traced)");
            let scene = scenes::builtin(id).map_err(|e| AssetError::Load { id: id.into(), reason: e.to_string() })?;
            return path_traced(scene.scene, &self.options)
                .map_err(|reason| AssetError::Load { id: id.into(), reason });
        }
        let extensions = self
            .formats
            .iter()
            .map(|(ext, _, _)| ext.as_str())
            .chain(PENDING_FORMATS.iter().copied())
            .collect::<Vec<_>>()
            .join("|");
        Err(AssetError::Unknown { id: id.into(), dir: self.dir.clone(), extensions })
    }
}

/// The reference path tracer over `scene` as a kernel.
pub fn path_traced(scene: nephele_pathtracer::Scene, options: &AssetOptions) -> Result<Kernel, String> {
    assets::path_traced(scene, &options.load).map_err(|e| e.to_string())
}

impl AssetLoader for DirAssetLoader {
    fn kernel_kinds(&self) -> Vec<String> {
        let mut kinds: Vec<String> = vec!["pathtrace".into()];
        for (_, kind, _) in &self.formats {
            if !kinds.iter().any(|k| k == kind) {
                kinds.push((*kind).into());
            }
        }
        kinds
    }

    fn load(&self, asset_id: &str) -> Result<Kernel, AssetError> {
        validate::asset_id(asset_id)?;
        let slot = {
            let mut cache = self.cache.lock().map_err(|_| poisoned(asset_id))?;
            let (slots, order) = &mut *cache;
            if let Some(slot) = slots.get(asset_id) {
                slot.clone()
            } else {
                if order.len() >= self.options.max_cached.max(1) {
                    let oldest = order.remove(0);
                    slots.remove(&oldest);
                }
                order.push(asset_id.to_string());
                slots.entry(asset_id.to_string()).or_default().clone()
            }
        };
        // One loader per id at a time; others wait for it and share the kernel. Failures are
        // not cached: the file may appear later.
        let mut guard = slot.lock().map_err(|_| poisoned(asset_id))?;
        if let Some(kernel) = guard.as_ref() {
            return Ok(kernel.clone());
        }
        let kernel = self.load_uncached(asset_id)?;
        *guard = Some(kernel.clone());
        Ok(kernel)
    }
}

fn poisoned(id: &str) -> AssetError {
    AssetError::Load { id: id.into(), reason: "a previous load of this asset panicked".into() }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn loader(dir: &Path) -> DirAssetLoader {
        DirAssetLoader::new(
            dir,
            AssetOptions {
                load: LoadOptions { pathtrace_spp: 1, pathtrace_bounces: 1, ..LoadOptions::default() },
                max_cached: 2,
            },
        )
        .expect("loader")
    }

    #[test]
    fn builtin_scenes_load_once_and_are_shared() {
        let dir = tempfile::tempdir().expect("tempdir");
        let loader = loader(dir.path());
        let a = loader.load("diffuse").expect("diffuse");
        let b = loader.load("diffuse").expect("diffuse again");
        assert!(Arc::ptr_eq(&a, &b));
        assert_eq!(a.kind(), "pathtrace");
        assert!(loader.kernel_kinds().contains(&"pathtrace".to_string()));
    }

    #[test]
    fn hostile_and_unknown_ids_are_clear_errors() {
        let dir = tempfile::tempdir().expect("tempdir");
        let loader = loader(dir.path());
        for bad in ["../diffuse", "..", "a/b", "/etc/passwd", ".hidden", "x..y", ""] {
            let err = loader.load(bad).expect_err(bad);
            assert!(matches!(err, AssetError::InvalidId(_)), "{bad}: {err}");
            assert_eq!(err.code(), ErrorCode::InvalidField);
        }
        let err = loader.load("no-such-asset").expect_err("unknown");
        assert!(matches!(err, AssetError::Unknown { .. }));
        assert_eq!(err.code(), ErrorCode::UnknownAsset);
        assert!(err.to_string().contains("no-such-asset"), "{err}");
    }

    #[test]
    fn corrupt_neural_assets_are_load_errors_and_files_win_over_builtins() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join("diffuse.nolf"), b"not an asset").expect("write");
        std::fs::write(dir.path().join("knot.ngp"), b"NGP?").expect("write");
        let mut loader = loader(dir.path());
        let err = loader.load("diffuse").expect_err("corrupt");
        assert!(matches!(err, AssetError::Load { .. }), "{err}");
        assert!(matches!(loader.load("knot").expect_err("corrupt"), AssetError::Load { .. }));
        // The extension point: a handler for the format makes the file load.
        loader.register_format(
            "nolf",
            "inolf",
            Arc::new(|_path, options| {
                let scene = scenes::builtin("glossy").map_err(|e| e.to_string())?;
                path_traced(scene.scene, options)
            }),
        );
        assert!(loader.load("diffuse").is_ok());
        assert!(loader.kernel_kinds().contains(&"inolf".to_string()));
    }

    #[test]
    fn a_nelf_asset_is_served_and_an_i_nolf_of_the_same_name_comes_first() {
        use nephele_kernels::nelf::{MatterGrid, MatterPlacement, NelfModel, RaySampling};
        use nephele_kernels::ngp::OccupancyGrid;
        let dir = tempfile::tempdir().expect("tempdir");
        let sampling = RaySampling { points: 4, frequencies: 2, min: [-1.0; 3], max: [1.0; 3] };
        let placement = MatterPlacement { min: [-1.0; 3], size: 2.0, step: 0.01, resolution: 16 };
        let matter = MatterGrid::new(placement, OccupancyGrid::filled(16, true)).expect("matter");
        let model = NelfModel::initial(sampling, matter, 8, 1, 1).expect("model");
        model.save(&dir.path().join("toy.nelf")).expect("save");
        let loader = loader(dir.path());
        assert!(loader.kernel_kinds().contains(&"nelf".to_string()));
        assert_eq!(loader.load("toy").expect("nelf").kind(), "nelf");
        // Both formats for one id: the i-NOLF file is the one loaded (the registry's order).
        model.save(&dir.path().join("twin.nelf")).expect("save");
        std::fs::write(dir.path().join("twin.nolf"), b"not an asset").expect("write");
        assert!(matches!(loader.load("twin").expect_err("the .nolf is read"), AssetError::Load { .. }));
    }

    #[cfg(unix)]
    #[test]
    fn symlinks_out_of_the_directory_are_refused() {
        let outside = tempfile::tempdir().expect("tempdir");
        let target = outside.path().join("secret.glb");
        std::fs::write(&target, b"glTF").expect("write");
        let dir = tempfile::tempdir().expect("tempdir");
        std::os::unix::fs::symlink(&target, dir.path().join("evil.glb")).expect("symlink");
        let err = loader(dir.path()).load("evil").expect_err("escape");
        assert!(matches!(err, AssetError::Escapes { .. }), "{err}");
    }

    #[test]
    fn broken_files_are_load_errors_and_not_cached() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join("broken.glb"), b"garbage").expect("write");
        let loader = loader(dir.path());
        let err = loader.load("broken").expect_err("garbage glb");
        assert!(matches!(err, AssetError::Load { .. }), "{err}");
        assert_eq!(err.code(), ErrorCode::AssetLoadFailed);
        assert!(loader.load("broken").is_err());
    }

    #[test]
    fn the_cache_is_bounded() {
        let dir = tempfile::tempdir().expect("tempdir");
        let loader = loader(dir.path());
        let first = loader.load("diffuse").expect("diffuse");
        loader.load("glossy").expect("glossy");
        loader.load("shell").expect("shell");
        let again = loader.load("diffuse").expect("diffuse reloaded");
        assert!(!Arc::ptr_eq(&first, &again), "evicted and rebuilt");
    }
}
