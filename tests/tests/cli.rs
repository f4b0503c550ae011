//! The `nephele` command as a user runs it: real processes, real files.

use nephele_tests::{nephele_err, nephele_ok, shared_data};
use nephele_train::dataset;

#[test]
fn help_explains_every_subcommand() {
    let help = nephele_ok(&["--help"]);
    for sub in ["scenes", "pathtrace", "dataset", "eval", "bench"] {
        assert!(help.contains(sub), "--help lacks {sub}:\n{help}");
    }
    for sub in [
        &["pathtrace", "--help"][..],
        &["dataset", "render", "--help"],
        &["eval", "--help"],
        &["bench", "reference", "--help"],
    ] {
        let text = nephele_ok(sub);
        assert!(text.contains("Usage"), "{sub:?}");
    }
}

#[test]
fn scenes_lists_every_builtin_scene() {
    let list = nephele_ok(&["scenes"]);
    for name in nephele_pathtracer::scenes::names() {
        assert!(list.contains(name), "{name} missing from:\n{list}");
    }
}

#[test]
fn dataset_render_then_load_then_eval() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("ds");
    let out_str = out.to_str().expect("utf-8 path");
    nephele_ok(&[
        "dataset",
        "render",
        "--scene",
        "diffuse",
        "--views",
        "3",
        "--test-views",
        "2",
        "--size",
        "32x24",
        "--spp",
        "2",
        "--depth",
        "--out",
        out_str,
    ]);
    let train = dataset::load_split(&out, "train", 1).expect("train split loads");
    assert_eq!(train.views.len(), 3);
    assert_eq!((train.views[0].image.width(), train.views[0].image.height()), (32, 24));
    assert!(train.views.iter().all(|v| v.depth.is_some()), "depth written and referenced");
    let alphas: Vec<f32> = train.views[0].image.pixels().iter().map(|p| p[3]).collect();
    assert!(alphas.contains(&0.0) && alphas.contains(&1.0), "an object on a transparent background");
    let test = dataset::load_split(&out, "test", 1).expect("test split loads");
    assert_eq!(test.views.len(), 2);

    // Identical folders: every image is a perfect match.
    let test_dir = out.join("test");
    let test_str = test_dir.to_str().expect("utf-8");
    let report = nephele_ok(&["eval", "--pred", test_str, "--gt", test_str]);
    assert!(report.contains("identical"), "{report}");

    // A second render with another seed differs by noise only: high but finite PSNR.
    let other = dir.path().join("other");
    nephele_ok(&[
        "dataset",
        "render",
        "--scene",
        "diffuse",
        "--views",
        "3",
        "--test-views",
        "2",
        "--size",
        "32x24",
        "--spp",
        "2",
        "--seed",
        "0",
        "--out",
        other.to_str().expect("utf-8"),
    ]);
    // Same seed: same images, bit for bit.
    let a = std::fs::read(out.join("test/r_1.png")).expect("read");
    let b = std::fs::read(other.join("test/r_1.png")).expect("read");
    assert_eq!(a, b, "rendering is deterministic for a seed");

    // Refuses to write into a non-empty folder without --force.
    let err =
        nephele_err(&["dataset", "render", "--scene", "diffuse", "--views", "1", "--size", "8x8", "--out", out_str]);
    assert!(err.contains("not empty"), "{err}");
}

#[test]
fn shared_lego_dataset_loads_downscaled() {
    let lego = shared_data().join("lego");
    let info = nephele_ok(&["dataset", "info", lego.to_str().expect("utf-8"), "--downscale", "8"]);
    assert!(info.contains("80 views 100x100"), "{info}");
}

#[test]
fn pathtrace_writes_every_output() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().to_str().expect("utf-8");
    let text = nephele_ok(&[
        "pathtrace",
        "--scene",
        "shell",
        "--size",
        "24x16",
        "--spp",
        "2",
        "--aov",
        "color,direct,alpha,depth,position,normal,albedo",
        "--exr",
        "--out",
        out,
    ]);
    assert!(text.contains("samples/s"), "{text}");
    for file in [
        "color.png",
        "color.exr",
        "direct.png",
        "direct.exr",
        "alpha.exr",
        "depth.exr",
        "position.exr",
        "normal.exr",
        "albedo.exr",
    ] {
        assert!(dir.path().join(file).is_file(), "{file} missing");
    }
}

#[test]
fn bad_input_gets_a_clear_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().to_str().expect("utf-8");
    let not_a_folder = dir.path().join("a-file");
    std::fs::write(&not_a_folder, b"x").expect("write");
    let not_a_folder = not_a_folder.to_str().expect("utf-8");
    let cases: &[(&[&str], &str)] = &[
        (&["pathtrace", "--size", "0x10", "--out", out], "positive"),
        (&["pathtrace", "--size", "abc", "--out", out], "WIDTHxHEIGHT"),
        (&["pathtrace", "--scene", "no-such-scene", "--out", out], "diffuse"),
        (&["pathtrace", "--scene", "diffuse", "--spp", "0", "--size", "4x4", "--out", out], "samples per pixel"),
        (&["pathtrace", "--scene", "diffuse", "--fov-y", "0", "--size", "4x4", "--out", out], "fov"),
        (
            &["pathtrace", "--scene", "diffuse", "--eye", "0,0,0", "--target", "0,0,0", "--size", "4x4", "--out", out],
            "camera",
        ),
        (&["pathtrace", "--scene", "diffuse", "--aov", "colour", "--size", "4x4", "--out", out], "unknown output"),
        (&["pathtrace", "--scene", "/nonexistent/model.gltf", "--out", out], "model.gltf"),
        (&["eval", "--pred", "/nonexistent/pred", "--gt", out], "/nonexistent/pred"),
        (&["eval", "--pred", out, "--gt", out, "--background", "3,0,0"], "[0, 1]"),
        (&["dataset", "info", out], "transforms"),
        (&["dataset", "render", "--scene", "diffuse", "--views", "0", "--out", out], "at least 1"),
        (&["--threads", "0", "scenes"], "threads"),
        (&["up", "--scene", "no-such-scene", "--bake", "off"], "known scenes: default"),
        (&["up", "--bake", "sometimes"], "standard"),
        (&["up", "--workers", "0", "--bake", "off"], "at least 1"),
        (&["up", "--assets", not_a_folder, "--bake", "off"], "creating the asset folder"),
    ];
    for (args, expected) in cases {
        let err = nephele_err(args);
        assert!(err.contains(expected), "nephele {args:?}: expected '{expected}' in:\n{err}");
        assert!(!err.contains("panicked"), "nephele {args:?} panicked:\n{err}");
    }
}

#[test]
fn bench_reference_runs_on_a_tiny_image() {
    let text = nephele_ok(&[
        "bench",
        "reference",
        "--size",
        "16x16",
        "--spp",
        "1",
        "--reference-spp",
        "4",
        "--scenes",
        "diffuse,furnace",
    ]);
    assert!(text.contains("tri/ray") && text.contains("furnace"), "{text}");
}

/// `nephele dataset gi` for both lightings, then again: the second run finds every frame and
/// renders none; other settings in the same folder are refused with a clear message.
#[test]
fn dataset_gi_renders_both_lightings_and_resumes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("gi");
    let out_str = out.to_str().expect("utf-8 path");
    let args = [
        "dataset",
        "gi",
        "--single",
        "2",
        "--stereo-pairs",
        "1",
        "--train-pairs",
        "1",
        "--size",
        "16x12",
        "--spp",
        "2",
        "--out",
        out_str,
    ];
    let first = nephele_ok(&args);
    assert!(first.contains("day: 6 frames rendered, 0 already there"), "{first}");
    assert!(first.contains("night: 6 frames rendered, 0 already there"), "{first}");
    for lighting in ["day", "night"] {
        let manifest = nephele_train::gi::data::read_manifest(&out.join(lighting)).expect("manifest");
        assert_eq!(manifest.spec.scene, format!("room-{lighting}"));
        for frame in &manifest.frames {
            let buffers = nephele_train::gi::data::load_frame(&out.join(lighting), frame).expect("frame loads");
            assert_eq!((buffers.width, buffers.height), (16, 12));
        }
    }
    let again = nephele_ok(&args);
    assert!(again.contains("day: 0 frames rendered, 6 already there"), "{again}");
    let err =
        nephele_err(&["dataset", "gi", "--lighting", "day", "--single", "3", "--size", "16x12", "--out", out_str]);
    assert!(err.contains("other settings"), "{err}");
    let err = nephele_err(&["dataset", "gi", "--lighting", "dusk", "--out", out_str]);
    assert!(err.contains("dusk"), "{err}");

    // The single-eye teacher trains on it, checkpoints, and a second run resumes.
    let day = out.join("day");
    let model = dir.path().join("day.ngi");
    let (day_str, model_str) = (day.to_str().expect("utf-8"), model.to_str().expect("utf-8"));
    let train = [
        "train",
        "gi",
        "--data",
        day_str,
        "--out",
        model_str,
        "--steps",
        "20",
        "--batch",
        "1",
        "--crop",
        "8",
        "--channels",
        "4,8",
        "--checkpoint-every",
        "10",
    ];
    let report = nephele_ok(&train);
    assert!(report.contains("after 20 steps") && report.contains("dB on the training frames"), "{report}");
    let loaded = nephele_kernels::gi::GiModel::load(&model).expect("the model loads");
    assert_eq!(loaded.network.config().channels, vec![4, 8]);
    assert!(dir.path().join("day.ckpt").is_file());
    let again = nephele_ok(&train);
    assert!(again.contains("resuming from") && again.contains("at step 20"), "{again}");
    let mut other = train.to_vec();
    other[7] = "30";
    let err = nephele_err(&other);
    assert!(err.contains("--restart"), "{err}");

    // Its stereo student, with and without the coherence loss, then the benchmark.
    let student = dir.path().join("day-stereo.ngi");
    let plain = dir.path().join("day-stereo-plain.ngi");
    for (path, weight) in [(&student, "1"), (&plain, "0")] {
        let mut args = train.to_vec();
        args[5] = path.to_str().expect("utf-8");
        args.extend(["--teacher", model_str, "--coherence-weight", weight]);
        let report = nephele_ok(&args);
        assert!(report.contains("1 training pairs") && report.contains("on 1 evaluation pairs"), "{report}");
    }
    let bench = nephele_ok(&[
        "bench",
        "gi",
        "--data",
        day_str,
        "--teacher",
        model_str,
        "--stereo",
        student.to_str().expect("utf-8"),
        "--stereo-no-coherence",
        plain.to_str().expect("utf-8"),
        "--size",
        "32x32",
        "--repeats",
        "1",
    ]);
    for needle in [
        "one stereo pass",
        "ratio",
        "single-eye model, run twice",
        "coherence error with the loss / without",
        "served at 0.5x, 2 spp, stereo pass",
        "served kernel, CPU, 32x32 per eye at 0.5x",
        "two bands of rows against the whole view",
        "GPU backend",
    ] {
        assert!(bench.contains(needle), "{needle}: {bench}");
    }
    let err = nephele_err(&["bench", "gi", "--data", day_str, "--teacher", model_str, "--stereo", model_str]);
    assert!(err.contains("not a stereo model"), "{err}");
}
