//! `nephele train` and `nephele render` as a user runs them, on a tiny dataset: the trained
//! field renders held-out poses that `nephele eval` can score.

use nephele_tests::{nephele_err, nephele_ok};

#[test]
fn train_render_eval_round_trip() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("ds");
    let data_str = data.to_str().expect("utf-8 path");
    nephele_ok(&[
        "dataset", "render", "--scene", "diffuse", "--views", "12", "--test-views", "2", "--size", "24x24", "--spp", "2",
        "--out", data_str,
    ]);
    let asset = dir.path().join("knot.ngp");
    let asset_str = asset.to_str().expect("utf-8 path");
    let report = nephele_ok(&[
        "train", "--dataset", data_str, "--out", asset_str, "--steps", "30", "--samples-per-step", "4096", "--table-log2",
        "14", "--levels", "8", "--finest", "128", "--occupancy", "32", "--steps-per-diagonal", "256",
    ]);
    assert!(report.contains("steps/s") && report.contains("PSNR"), "{report}");
    assert!(asset.is_file());

    let renders = dir.path().join("renders");
    let renders_str = renders.to_str().expect("utf-8 path");
    let transforms = data.join("transforms_test.json");
    let out = nephele_ok(&["render", "--asset", asset_str, "--transforms", transforms.to_str().expect("utf-8"), "--out", renders_str]);
    assert!(out.contains("ms per frame") && out.contains("'ngp'"), "{out}");
    // Named like the ground truth, at the ground truth's size, so eval pairs them up.
    for name in ["r_0.png", "r_1.png"] {
        assert!(renders.join(name).is_file(), "{name} missing");
    }
    let gt = data.join("test");
    let eval = nephele_ok(&["eval", "--pred", renders_str, "--gt", gt.to_str().expect("utf-8")]);
    assert!(eval.contains("mean of 2"), "{eval}");

    // Not an asset: a clear error, no panic.
    let bogus = dir.path().join("bogus.bin");
    std::fs::write(&bogus, b"definitely not an asset file").expect("write");
    let err = nephele_err(&["render", "--asset", bogus.to_str().expect("utf-8"), "--transforms", transforms.to_str().expect("utf-8"), "--out", renders_str]);
    assert!(err.contains("not a known asset format"), "{err}");
    // A truncated field file is refused by its loader.
    let bytes = std::fs::read(&asset).expect("read");
    std::fs::write(&bogus, &bytes[..bytes.len() / 3]).expect("write");
    let err = nephele_err(&["render", "--asset", bogus.to_str().expect("utf-8"), "--transforms", transforms.to_str().expect("utf-8"), "--out", renders_str]);
    assert!(err.contains("truncated"), "{err}");
}
