//! The first start of `nephele up`: the default scene's objects baked into i-NOLF assets.
//!
//! No baked assets ship with Nephele (they are tens of MiB each). On first start, `up` bakes
//! every built-in object of the scene it serves and keeps the assets in a cache folder, so
//! later starts reuse them. Each object goes through the library calls that `nephele dataset
//! render` and `nephele bake` make, with the recipe's typed values
//! ([`nephele_train::synth::render_dataset`], [`nephele_train::inolf::pipeline::bake`]),
//! then the asset is scored on the held-out views (PSNR against the path tracer's images)
//! and moved into place. An asset is written as `NAME.nolf.part-PID` and renamed once complete,
//! so an interrupted bake leaves no half asset behind, and objects already baked are kept.
//! The workers resolve an object's asset id to `DIR/NAME.nolf` before the built-in
//! (path-traced) scene of the same name, so a baked object is served by the i-NOLF kernel.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use nephele_kernels::environment::GiServeSettings;
use nephele_kernels::inolf::kernel::InolfKernel;
use nephele_train::inolf::pipeline::{BakeRecipe, bake};
use nephele_train::score::{MARCH_STRIDE_BUDGET_DB, choose_march_stride, march_stride_scores};
use nephele_train::synth::DatasetSpec;

use super::bake::Bars;

use crate::progress::Progress;

/// How hard the first start works on each object.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BakeQuality {
    /// 128x128 training views, a few minutes per object on two cores.
    Standard,
    /// 48x48 views and a few hundred steps, seconds per object: a blurry but real i-NOLF
    /// asset, for trying the service out and for the tests.
    Quick,
    /// Bake nothing: objects without a `.nolf` asset are path traced by the workers.
    Off,
}

/// The settings of one quality: the dataset rendered of each object, and its bake.
#[derive(Debug, Clone, PartialEq)]
pub struct Recipe {
    /// Side of the square training and test views.
    pub size: u32,
    pub views: usize,
    pub test_views: usize,
    pub spp: u32,
    /// Samples per pixel of the held-out views, the bake's reference (0: `spp`).
    pub test_spp: u32,
    pub bounces: u32,
    /// The bake; the rest of `nephele bake`'s defaults. `cube_res` 5 (4 steps per cell) is
    /// finer than a pixel of the training views here, as good as 8 on held-out views, and
    /// marches 1.5x faster with half the asset (BENCHMARKS.md, "First start"). `psh_res`
    /// 128 for the built-in objects' 128x128 path-traced views, whose 32-spp noise a larger
    /// lattice learns too (held-out PSNR +0.05 to +1.1 dB against 256 on every object, half
    /// the asset; BENCHMARKS.md, "table 5 on the built-in objects").
    pub bake: BakeRecipe,
}

impl Recipe {
    /// The dataset of a built-in object: `views` + `test_views` views of `size` squared.
    pub fn dataset_spec(&self) -> DatasetSpec {
        DatasetSpec {
            views: self.views,
            test_views: self.test_views,
            width: self.size,
            height: self.size,
            spp: self.spp,
            test_spp: self.test_spp,
            bounces: self.bounces,
            seed: 0,
            full_sphere: false,
            depth: false,
        }
    }
}

impl BakeQuality {
    pub fn recipe(self) -> Option<Recipe> {
        match self {
            BakeQuality::Standard => Some(Recipe {
                size: 128,
                views: 64,
                test_views: 4,
                spp: 32,
                // The 4 held-out views converged further (a path tracer's noise at 32 spp
                // alone caps the glossy object's PSNR near 26 dB): about 20 s more in all.
                test_spp: 256,
                bounces: 6,
                bake: BakeRecipe {
                    field_steps: 400,
                    field_table_log2: 17,
                    field_levels: 16,
                    field_finest: 1024,
                    field_samples: 1 << 15,
                    head_steps: 1200,
                    batch: 4096,
                    // 16 cells of 12 voxels (a 192^3 sample lattice, the same as 48 cells
                    // of 4 before 2026-12-05): a ray crosses half the cells, and the DDA over
                    // cells, not the samples, was the glass shell's cost (BENCHMARKS.md).
                    cubes: 16,
                    cube_res: 13,
                    cube_probe: 12,
                    psh_res: 128,
                    // Measured on the lego only; the objects' numbers are without them.
                    pseudo_views: 0,
                    diffuse_blend: false,
                    ..BakeRecipe::default()
                },
            }),
            BakeQuality::Quick => Some(Recipe {
                size: 48,
                views: 24,
                test_views: 2,
                spp: 4,
                test_spp: 16,
                bounces: 3,
                bake: BakeRecipe {
                    field_steps: 40,
                    field_table_log2: 14,
                    field_levels: 8,
                    field_finest: 128,
                    field_samples: 1 << 13,
                    head_steps: 150,
                    batch: 1024,
                    cubes: 24,
                    cube_res: 5,
                    psh_res: 96,
                    pseudo_views: 0,
                    diffuse_blend: false,
                    ..BakeRecipe::default()
                },
            }),
            BakeQuality::Off => None,
        }
    }

    /// Cache subfolder name: assets of different qualities (or of an older bake recipe) never
    /// mix. Bump the suffix when a recipe or the asset format changes.
    pub fn folder(self) -> &'static str {
        match self {
            BakeQuality::Standard => "standard-v8",
            BakeQuality::Quick => "quick-v6",
            BakeQuality::Off => "path-traced",
        }
    }
}

/// Where baked assets are kept between starts: `$NEPHELE_CACHE`, else
/// `$XDG_CACHE_HOME/nephele`, else `$HOME/.cache/nephele`, else the temporary folder; then
/// `assets/<quality>`.
pub fn default_asset_dir(quality: BakeQuality) -> PathBuf {
    cache_root().join("assets").join(quality.folder())
}

/// Nephele's cache folder: `$NEPHELE_CACHE`, else `$XDG_CACHE_HOME/nephele`, else
/// `~/.cache/nephele`.
pub fn cache_root() -> PathBuf {
    let env = |name: &str| std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from);
    env("NEPHELE_CACHE")
        .or_else(|| env("XDG_CACHE_HOME").map(|d| d.join("nephele")))
        .or_else(|| env("HOME").map(|d| d.join(".cache").join("nephele")))
        .unwrap_or_else(|| std::env::temp_dir().join("nephele-cache"))
}

/// What the first start found or made for one object.
#[derive(Debug, Clone, PartialEq)]
pub struct BakedObject {
    pub name: String,
    pub path: PathBuf,
    /// Mean PSNR of the asset on the held-out views (at the march stride it is served with),
    /// when it was baked by this call.
    pub psnr_db: Option<f64>,
    /// The march stride the bake chose ([`choose_march_stride`]), when it was baked by this call.
    pub march_stride: Option<u32>,
    pub seconds: f64,
}

/// Whether `path` holds an asset the workers will load (every size and checksum verified).
/// The first start of an environment (issue 13): its GI dataset and the two trainings of
/// `nephele dataset gi` and `nephele train gi`, small enough for two cores.
#[derive(Debug, Clone, PartialEq)]
pub struct GiRecipe {
    /// Side of the square dataset frames.
    pub size: u32,
    pub single: usize,
    pub eval_pairs: usize,
    pub train_pairs: usize,
    pub spp: u32,
    pub bounces: u32,
    pub teacher_steps: u32,
    pub student_steps: u32,
    /// Side of the training crops (a multiple of 4, at most `size`).
    pub crop: usize,
    /// Train on inputs rendered as the farm serves them, at this many samples
    /// (`nephele train gi --input-spp`); `None`: the dataset's converged direct light.
    pub input_spp: Option<u32>,
    /// Written into the models' headers (`training.recipe`): a model of another recipe is
    /// trained again at the next start (the objects' assets stay).
    pub version: &'static str,
}

impl BakeQuality {
    /// Standard: 64x64 frames at 64 spp, the networks trained on inputs rendered as the farm
    /// serves them (2 samples) towards the converged target, the teacher 4000 steps, the
    /// student 8000 from the teacher on 64 stereo pairs (about 2.5 minutes of training on two
    /// cores; served at half resolution 1.6-2.1 dB above the earlier 600 / 1000 steps on clean
    /// inputs: BENCHMARKS.md, "2026-12-06f"; the student within 0.3 dB of its teacher as
    /// served, day and night: "2026-12-06h" (4000 steps left the night's 0.65 dB under it)).
    /// Quick: seconds, a barely trained model, for trying the service and for the tests.
    pub fn gi_recipe(self) -> Option<GiRecipe> {
        match self {
            BakeQuality::Standard => Some(GiRecipe {
                size: 64,
                single: 48,
                eval_pairs: 4,
                train_pairs: 64,
                spp: 64,
                bounces: 4,
                teacher_steps: 4000,
                student_steps: 8000,
                crop: 32,
                input_spp: Some(GiServeSettings::default().samples_per_pixel),
                version: "standard-gi-v5",
            }),
            BakeQuality::Quick => Some(GiRecipe {
                size: 32,
                single: 8,
                eval_pairs: 1,
                train_pairs: 4,
                spp: 8,
                bounces: 2,
                teacher_steps: 60,
                student_steps: 60,
                crop: 16,
                input_spp: Some(GiServeSettings::default().samples_per_pixel),
                version: "quick-gi-v4",
            }),
            BakeQuality::Off => None,
        }
    }
}

/// Whether `path` holds a GI model the workers serve, with its stereo twin, both trained by
/// the recipe `version`.
fn environment_loads(path: &Path, version: &str) -> bool {
    use nephele_kernels::environment::GiKernel;
    let of_recipe = |training: &serde_json::Value| training.get("recipe").and_then(|r| r.as_str()) == Some(version);
    path.is_file()
        && GiKernel::load(path, GiServeSettings::default()).is_ok_and(|k| match k.models() {
            (single, Some(stereo)) => of_recipe(&single.header.training) && of_recipe(&stereo.header.training),
            _ => false,
        })
}

/// Makes sure `dir/<name>.ngi` and `dir/<name>.stereo.ngi` exist for a built-in environment
/// (`room-day`, `room-night`), training the missing ones; `None` with `--bake off` (the
/// workers then path trace the room).
pub fn ensure_environment(
    dir: &Path,
    name: &str,
    quality: BakeQuality,
    progress: &Progress,
) -> Result<Option<BakedObject>> {
    use nephele_kernels::environment::stereo_path;
    use nephele_train::gi::data::{GiSpec, render_gi_dataset};
    use nephele_train::gi::stereo::{StudentOptions, load_pairs, train_stereo};
    use nephele_train::gi::train::{GiTrainOptions, evaluate_single_eye, load_single_eye, train_single_eye};

    let Some(recipe) = quality.gi_recipe() else { return Ok(None) };
    let path = dir.join(format!("{name}.ngi"));
    if environment_loads(&path, recipe.version) {
        return Ok(Some(BakedObject { name: name.into(), path, psnr_db: None, march_stride: None, seconds: 0.0 }));
    }
    println!(
        "first start: training the global-illumination model of '{name}' into {} (recipe {}; later starts reuse it)",
        path.display(),
        recipe.version
    );
    let start = Instant::now();
    std::fs::create_dir_all(dir).with_context(|| format!("creating the asset folder {}", dir.display()))?;
    let work = tempfile::Builder::new()
        .prefix(&format!(".bake-{}-{name}-", std::process::id()))
        .tempdir_in(dir)
        .context("a scratch folder for the dataset")?;
    let data = work.path().join("dataset");
    let spec = GiSpec {
        scene: name.into(),
        single: recipe.single,
        stereo_pairs: recipe.eval_pairs,
        train_pairs: recipe.train_pairs,
        width: recipe.size,
        height: recipe.size,
        fov_y: 70f32.to_radians(),
        spp: recipe.spp,
        bounces: recipe.bounces,
        seed: 0,
    };
    let frames = (spec.single + 2 * (spec.stereo_pairs + spec.train_pairs)) as u64;
    let bar = progress.bar(frames * u64::from(spec.height), &format!("GI dataset, {name}"), "rows");
    render_gi_dataset(&spec, &data, &|rows| bar.inc(u64::from(rows)))?;
    bar.finish_and_clear();

    let (train, held_out, features, _) = load_single_eye(&data, recipe.input_spp)?;
    let options = GiTrainOptions {
        steps: recipe.teacher_steps,
        crop: recipe.crop,
        learning_rate: 2e-3,
        ..GiTrainOptions::default()
    };
    let bar = progress.bar(u64::from(options.steps), "GI teacher", "steps");
    let (mut teacher, _) = train_single_eye(
        &train,
        features,
        &options,
        None,
        0,
        &mut |s| bar.set_position(u64::from(s.step)),
        &mut |_| Ok(()),
    )?;
    bar.finish_and_clear();
    teacher.header.scene = Some(name.into());
    let psnr = if held_out.is_empty() { f64::NAN } else { evaluate_single_eye(&teacher, &held_out)? };

    let pairs = load_pairs(&data, &features, true, recipe.input_spp)?;
    let options = GiTrainOptions { steps: recipe.student_steps, learning_rate: 1e-3, ..options };
    let bar = progress.bar(u64::from(options.steps), "GI stereo student", "steps");
    let (student, _) = train_stereo(
        &teacher,
        &pairs,
        &options,
        StudentOptions::default(),
        None,
        0,
        &mut |s| bar.set_position(u64::from(s.step)),
        &mut |_| Ok(()),
    )?;
    bar.finish_and_clear();
    let mut student = student;
    for model in [&mut teacher, &mut student] {
        let training = std::mem::take(&mut model.header.training);
        model.header.training = serde_json::json!({ "recipe": recipe.version, "run": training });
    }
    // The student first: the single-eye model's presence says the pair is complete.
    let scratch = |p: &Path| p.with_extension(format!("part-{}", std::process::id()));
    for (model, target) in [(&student, stereo_path(&path)), (&teacher, path.clone())] {
        let part = scratch(&target);
        model.save(&part).with_context(|| format!("writing {}", part.display()))?;
        std::fs::rename(&part, &target).with_context(|| format!("moving the model to {}", target.display()))?;
    }
    println!("'{name}': {psnr:.2} dB PSNR on {} held-out frames (GI model against the path tracer)", held_out.len());
    Ok(Some(BakedObject {
        name: name.into(),
        path,
        psnr_db: Some(psnr),
        march_stride: None,
        seconds: start.elapsed().as_secs_f64(),
    }))
}

fn loads(path: &Path) -> bool {
    path.is_file() && InolfKernel::load(path).is_ok()
}

/// Makes sure `dir/<name>.nolf` exists for every name, baking the missing ones (a corrupt or
/// truncated one is baked again). Returns one line of account per object.
pub fn ensure_baked(
    dir: &Path,
    names: &[String],
    quality: BakeQuality,
    progress: &Progress,
) -> Result<Vec<BakedObject>> {
    let Some(recipe) = quality.recipe() else { return Ok(Vec::new()) };
    std::fs::create_dir_all(dir).with_context(|| format!("creating the asset folder {}", dir.display()))?;
    remove_stale_scratch(dir);
    let mut done = Vec::with_capacity(names.len());
    let missing: Vec<&String> = names.iter().filter(|n| !loads(&dir.join(format!("{n}.nolf")))).collect();
    let mut index = 0;
    for name in names {
        let path = dir.join(format!("{name}.nolf"));
        if !missing.contains(&name) {
            done.push(BakedObject { name: name.clone(), path, psnr_db: None, march_stride: None, seconds: 0.0 });
            continue;
        }
        index += 1;
        println!(
            "first start: baking '{name}' ({index} of {}) into {} (recipe {}; later starts reuse it)",
            missing.len(),
            path.display(),
            quality.folder()
        );
        done.push(
            bake_object(dir, name, &recipe, progress)
                .with_context(|| format!("baking the built-in object '{name}'"))?,
        );
    }
    Ok(done)
}

/// The process id in a scratch name of ours: `.bake-PID-...` (dataset folders) or
/// `NAME.nolf.part-PID` (assets being written).
fn scratch_owner(file_name: &str) -> Option<i32> {
    if let Some(rest) = file_name.strip_prefix(".bake-") {
        return rest.split('-').next()?.parse().ok();
    }
    file_name.rsplit_once(".nolf.part-")?.1.parse().ok()
}

/// Removes what an interrupted bake (Ctrl-C, a crash) left in `dir`: scratch entries whose
/// process is gone. Those of a live process (another first start) are left alone.
fn remove_stale_scratch(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = scratch_owner(&name).filter(|&pid| pid > 0) else { continue };
        // Signal 0 probes for the process; EPERM means it exists under another user.
        let probe = nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), None);
        if matches!(probe, Ok(()) | Err(nix::errno::Errno::EPERM)) {
            continue;
        }
        let path = entry.path();
        let removed = if path.is_dir() { std::fs::remove_dir_all(&path) } else { std::fs::remove_file(&path) };
        match removed {
            Ok(()) => tracing::info!(path = %path.display(), "removed what an interrupted bake left"),
            Err(e) => tracing::warn!(path = %path.display(), "could not remove what an interrupted bake left: {e}"),
        }
    }
}

/// Renders the dataset, bakes, scores and moves the asset into place.
fn bake_object(dir: &Path, name: &str, recipe: &Recipe, progress: &Progress) -> Result<BakedObject> {
    let start = Instant::now();
    let work = tempfile::Builder::new()
        .prefix(&format!(".bake-{}-{name}-", std::process::id()))
        .tempdir_in(dir)
        .context("a scratch folder for the dataset")?;
    let data = work.path().join("dataset");
    let scene = nephele_pathtracer::scenes::builtin(name)?;
    super::dataset::render_into(scene, name, &recipe.dataset_spec(), &data, progress)?;
    // Unique per process: two first starts sharing the cache folder do not write one file.
    let part = dir.join(format!("{name}.nolf.part-{}", std::process::id()));
    let views = super::bake::training_data(&data, "train", 1, 0, 0)?;
    println!("bake: {} views of {1}x{1} from {2}", views.views.len(), recipe.size, data.display());
    let baked = bake(&views, &data.display().to_string(), &recipe.bake, None, &mut Bars::new(progress))?;
    let mut asset = baked.asset;
    let scores = score_strides(&asset, &data).context("scoring the asset on the held-out views")?;
    anyhow::ensure!(!scores.is_empty(), "the dataset has no test views");
    let stride = choose_march_stride(&scores, MARCH_STRIDE_BUDGET_DB);
    let psnr = scores[stride as usize - 1];
    println!(
        "'{name}': {psnr:.2} dB PSNR on {} held-out views of {1}x{1} (i-NOLF against the path tracer) at march stride {stride}; every voxel {2:.2} dB, strides 1-{3}: {4}",
        recipe.test_views,
        recipe.size,
        scores[0],
        scores.len(),
        scores.iter().map(|p| format!("{p:.3}")).collect::<Vec<_>>().join(" / ")
    );
    nephele_kernels::inolf::heads::set_asset_march_stride(&mut asset, stride)?;
    asset.save(&part).with_context(|| format!("writing {}", part.display()))?;
    let path = dir.join(format!("{name}.nolf"));
    std::fs::rename(&part, &path).with_context(|| format!("moving the asset to {}", path.display()))?;
    Ok(BakedObject {
        name: name.into(),
        path,
        psnr_db: Some(psnr),
        march_stride: Some(stride),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Mean PSNR (over white) of the asset on the dataset's test views at every march stride
/// from 1 (every voxel) to the largest.
fn score_strides(asset: &nephele_kernels::inolf::asset::Asset, dataset: &Path) -> Result<Vec<f64>> {
    let kernel = InolfKernel::from_asset(asset.clone())?;
    let data = nephele_train::dataset::load_split(dataset, "test", 1)?;
    Ok(march_stride_scores(&kernel, &data.views, data.camera_angle_x)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_recipe_is_a_dataset_and_a_bake() {
        for quality in [BakeQuality::Standard, BakeQuality::Quick] {
            let r = quality.recipe().expect("a recipe");
            assert!(r.size >= 16 && r.views > 0 && r.test_views > 0 && r.bake.field_steps > 0 && r.bake.head_steps > 0);
            let spec = r.dataset_spec();
            assert_eq!((spec.views, spec.test_views, spec.width, spec.height), (r.views, r.test_views, r.size, r.size));
            assert_eq!((r.bake.seed, r.bake.psh_features), (1, 8));
            // Probes at every sample point of a cell: no thin matter between probes is lost.
            assert_eq!(r.bake.cube_probe, r.bake.cube_res - 1, "{:?}", r.bake);
        }
        assert!(BakeQuality::Off.recipe().is_none());
        assert_ne!(BakeQuality::Standard.folder(), BakeQuality::Quick.folder());
    }

    #[test]
    fn an_interrupted_bakes_scratch_is_removed_unless_its_process_lives() {
        assert_eq!(scratch_owner(".bake-123-diffuse-AbC"), Some(123));
        assert_eq!(scratch_owner("glossy.nolf.part-77"), Some(77));
        assert_eq!(scratch_owner("glossy.nolf"), None);
        assert_eq!(scratch_owner(".bake-x-glossy"), None);
        let dir = tempfile::tempdir().expect("tempdir");
        // No process has pid 2^22 + 1 (above Linux's pid_max default); ours is alive.
        let dead = 4_194_305;
        std::fs::create_dir(dir.path().join(format!(".bake-{dead}-diffuse-x"))).expect("mkdir");
        std::fs::write(dir.path().join(format!("diffuse.nolf.part-{dead}")), b"half").expect("write");
        let ours = dir.path().join(format!("shell.nolf.part-{}", std::process::id()));
        std::fs::write(&ours, b"in progress").expect("write");
        std::fs::write(dir.path().join("glossy.nolf"), b"kept").expect("write");
        remove_stale_scratch(dir.path());
        let mut left: Vec<String> = std::fs::read_dir(dir.path())
            .expect("read")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        assert_eq!(left, vec!["glossy.nolf".to_string(), format!("shell.nolf.part-{}", std::process::id())]);
    }

    #[test]
    fn a_corrupt_cached_asset_does_not_count_as_baked() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("diffuse.nolf");
        assert!(!loads(&path));
        std::fs::write(&path, b"NEPHNOLF but not really an asset").expect("write");
        assert!(!loads(&path));
    }
}
