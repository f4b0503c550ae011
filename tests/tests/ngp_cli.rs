//! `nephele train ngp` and `nephele render` as a user runs them, on a tiny dataset: the trained
//! field renders held-out poses that `nephele eval` can score.

use nephele_tests::{nephele_err, nephele_ok};

#[test]
fn train_render_eval_round_trip() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("ds");
    let data_str = data.to_str().expect("utf-8 path");
    nephele_ok(&[
        "dataset",
        "render",
        "--scene",
        "diffuse",
        "--views",
        "12",
        "--test-views",
        "2",
        "--size",
        "24x24",
        "--spp",
        "2",
        "--out",
        data_str,
    ]);
    let asset = dir.path().join("knot.ngp");
    let asset_str = asset.to_str().expect("utf-8 path");
    let report = nephele_ok(&[
        "train",
        "ngp",
        "--dataset",
        data_str,
        "--out",
        asset_str,
        "--steps",
        "30",
        "--samples-per-step",
        "4096",
        "--table-log2",
        "14",
        "--levels",
        "8",
        "--finest",
        "128",
        "--occupancy",
        "32",
        "--steps-per-diagonal",
        "256",
    ]);
    assert!(report.contains("steps/s") && report.contains("PSNR"), "{report}");
    assert!(asset.is_file());

    let renders = dir.path().join("renders");
    let renders_str = renders.to_str().expect("utf-8 path");
    let transforms = data.join("transforms_test.json");
    let out = nephele_ok(&[
        "render",
        "--asset",
        asset_str,
        "--transforms",
        transforms.to_str().expect("utf-8"),
        "--out",
        renders_str,
    ]);
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
    let err = nephele_err(&[
        "render",
        "--asset",
        bogus.to_str().expect("utf-8"),
        "--transforms",
        transforms.to_str().expect("utf-8"),
        "--out",
        renders_str,
    ]);
    assert!(err.contains("not a known asset format"), "{err}");
    // A truncated field file is refused by its loader.
    let bytes = std::fs::read(&asset).expect("read");
    std::fs::write(&bogus, &bytes[..bytes.len() / 3]).expect("write");
    let err = nephele_err(&[
        "render",
        "--asset",
        bogus.to_str().expect("utf-8"),
        "--transforms",
        transforms.to_str().expect("utf-8"),
        "--out",
        renders_str,
    ]);
    assert!(err.contains("truncated"), "{err}");
}

/// `nephele bake` then `nephele bench inolf` as a user runs them, on a tiny dataset: two
/// assets from one saved field (different PSH lattices), the ablation rows of NEPHELE
/// table 5 with their memory and query columns, the distance curve and the large frame;
/// and a NeLF distilled from the same field (`nephele distill`, resumed from its checkpoint
/// and pseudo-data cache) in the same table, rendered by `nephele render` as well.
#[test]
fn bake_then_bench_inolf_prints_the_ablation_rows() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = |name: &str| dir.path().join(name).to_str().expect("utf-8 path").to_owned();
    let (data, field, first, second) = (path("ds"), path("field.ngp"), path("a.nolf"), path("b.nolf"));
    nephele_ok(&[
        "dataset",
        "render",
        "--scene",
        "diffuse",
        "--views",
        "12",
        "--test-views",
        "2",
        "--size",
        "24x24",
        "--spp",
        "2",
        "--out",
        &data,
    ]);
    let tiny = [
        "--dataset",
        &data,
        "--downscale",
        "1",
        "--field-steps",
        "30",
        "--field-table-log2",
        "14",
        "--field-levels",
        "8",
        "--field-finest",
        "128",
        "--field-samples",
        "4096",
        "--steps",
        "40",
        "--batch",
        "512",
        "--cubes",
        "16",
        "--cube-res",
        "4",
        "--keep-diffuse-network",
    ];
    let report =
        nephele_ok(&[&["bake", "--out", &first, "--psh-res", "64", "--save-field", &field][..], &tiny].concat());
    assert!(report.contains("perfect spatial hash") && report.contains("at 64^3"), "{report}");
    // The heads also see the field's renders at new poses by default.
    assert!(report.contains("pseudo-views: 70 rendered by the radiance field"), "{report}");
    let report = nephele_ok(&[&["bake", "--out", &second, "--psh-res", "32", "--field", &field][..], &tiny].concat());
    assert!(report.contains("at 32^3"), "{report}");

    let nelf = path("c.nelf");
    let base = [
        "distill",
        "--field",
        &field,
        "--dataset",
        &data,
        "--downscale",
        "1",
        "--points",
        "4",
        "--frequencies",
        "2",
        "--width",
        "16",
        "--blocks",
        "1",
        "--pseudo-views",
        "4",
        "--rays-per-view",
        "64",
        "--steps",
        "20",
        "--fine-tune-steps",
        "10",
        "--batch",
        "64",
        "--hard-pool",
        "256",
        "--checkpoint-every",
        "10",
    ];
    let distill = [&base[..], &["--out", &nelf, "--eval-views", "1"]].concat();
    let report = nephele_ok(&distill);
    assert!(report.contains("pseudo-data: 256 rays rendered by the field from 4 poses"), "{report}");
    assert!(report.contains("W16 B1 (4 layers") && report.contains(": 30 steps"), "{report}");
    assert!(report.contains("held-out views (1): NeLF W16 B1") && report.contains("wrote"), "{report}");
    // Again: the finished checkpoint and the pseudo-data cache are reused.
    let again = nephele_ok(&distill);
    assert!(again.contains("resuming from") && again.contains("at step 30"), "{again}");
    assert!(again.contains("pseudo-data: 256 rays from the cache"), "{again}");
    let err = nephele_err(&[&distill[..], &["--seed", "9"]].concat());
    assert!(err.contains("other settings") && err.contains("--restart"), "{err}");
    let err = nephele_err(&[&distill[..], &["--hard-fraction", "2"]].concat());
    assert!(err.contains("hard-example fraction"), "{err}");
    // Sizes tried smallest first against a quality target no tiny network reaches: the last
    // is kept, and the report says so.
    let sized = path("sized.nelf");
    let tried = nephele_ok(&[&base[..], &["--out", &sized, "--sizes", "8x1,16x1", "--target-psnr", "99"]].concat());
    assert!(tried.contains("held-out views (1): NeLF W8 B1") && tried.contains("NeLF W16 B1"), "{tried}");
    assert!(tried.contains("no size reached --target-psnr 99.00 dB; keeping the last (W16 B1)"), "{tried}");
    let err = nephele_err(&[&base[..], &["--out", &sized, "--target-psnr", "20", "--eval-views", "0"]].concat());
    assert!(err.contains("needs held-out views"), "{err}");
    let renders = path("nelf-renders");
    let transforms = format!("{data}/transforms_test.json");
    let out = nephele_ok(&["render", "--asset", &nelf, "--transforms", &transforms, "--out", &renders]);
    assert!(out.contains("'nelf'"), "{out}");
    let mut truncated = std::fs::read(&nelf).expect("read");
    truncated.truncate(truncated.len() - 100);
    let broken = path("broken.nelf");
    std::fs::write(&broken, &truncated).expect("write");
    let err = nephele_err(&["render", "--asset", &broken, "--transforms", &transforms, "--out", &renders]);
    assert!(err.contains("checksum"), "{err}");

    let assets = format!("{first},{second}");
    let bench = ["bench", "inolf", "--field", &field, "--dataset", &data, "--downscale", "1", "--views", "2"];
    let out = nephele_ok(
        &[
            &bench[..],
            &[
                "--asset",
                &assets,
                "--nelf",
                &nelf,
                "--distances",
                "2,1",
                "--large-frame",
                "40x30",
                "--large-distance",
                "0.8",
            ],
        ]
        .concat(),
    );
    let row = |label: &str| -> Vec<f64> {
        let line = out.lines().find(|l| l.starts_with(label)).unwrap_or_else(|| panic!("no row '{label}' in:\n{out}"));
        line[label.len()..].split_whitespace().filter_map(|v| v.trim_end_matches(['x', '%']).parse().ok()).collect()
    };
    // Columns: PSNR, SSIM, model MiB, runtime MiB, ms/frame, rays/s, queries/ray, speed-up.
    let baseline = row("i-NGP baseline");
    let base = row("i-NOLF base (density network, diffuse MLP, PSH 64^3)");
    let cubes_mlp = row("+ density cubes (diffuse MLP, PSH 64^3)");
    let cubes = row("+ diffuse cubes (PSH 64^3)");
    let second_row = row("+ diffuse cubes (PSH 32^3, b.nolf)");
    let nelf_row = row("NeLF W16 D4 (K=4, L=2, c.nelf)");
    // At most one query per ray: the network, for rays that meet the field's occupied cells.
    assert!(nelf_row[6] <= 1.0, "{out}");
    assert!(out.contains("NeLF W16 D4 (K=4, L=2, c.nelf): 3173 FLOPs per network query"), "{out}");
    for r in [&baseline, &base, &cubes_mlp, &cubes, &second_row, &nelf_row] {
        assert_eq!(r.len(), 8, "{r:?} in:\n{out}");
        assert!(r.iter().all(|v| v.is_finite()) && r[0] > 5.0 && r[3] > 0.0, "{r:?} in:\n{out}");
    }
    // The density network costs many queries per ray; the cubes one per hitting ray at most.
    assert!(base[6] > 2.0 * cubes_mlp[6] && cubes_mlp[6] <= 1.0 && cubes[6] <= 1.0, "{out}");
    // The base row reads the field instead of the density cubes: a different model size.
    assert!((base[2] - cubes_mlp[2]).abs() > 1e-3, "{out}");
    assert!(out.contains("distance curve") && out.contains("large frame: 40x30"), "{out}");

    let err = nephele_err(&[&bench[..], &["--asset", &first, "--distances", "1,-2"]].concat());
    assert!(err.contains("'-2' is not a positive distance factor"), "{err}");
    // Refused before anything renders.
    let err = nephele_err(&[&bench[..], &["--asset", &first, "--large-frame", "40x30", "--large-distance=0"]].concat());
    assert!(err.contains("'0' is not a positive distance factor"), "{err}");
    let err = nephele_err(&[&bench[..], &["--asset", &first, "--large-frame", "0x30"]].concat());
    assert!(err.contains("positive"), "{err}");
    let missing = path("missing.nolf");
    let err = nephele_err(&[&bench[..], &["--asset", &format!("{first},{missing}")]].concat());
    assert!(err.contains("loading") && err.contains("missing.nolf"), "{err}");
    let skipped = nephele_ok(&[&bench[..], &["--distances", "none", "--asset", &second]].concat());
    assert!(
        !skipped.contains("distance curve") && skipped.contains("i-NOLF base (density network, diffuse MLP, PSH 32^3)"),
        "{skipped}"
    );

    // `bench kernel` times the march without the blend samples these heads keep (they blend
    // their diffuse colour by default) and says what keeping them costs.
    let out = nephele_ok(&["bench", "kernel", "--asset", &first, "--size", "32x24", "--views", "2", "--rounds", "1"]);
    for row in ["whole kernel, AVX2+FMA where present", "density march alone", "density march without blend samples"] {
        assert!(out.lines().any(|l| l.starts_with(row)), "no row '{row}' in:\n{out}");
    }
    assert!(
        out.contains("keeping the 8 blend samples (heads that blend their diffuse colour; this asset's heads do)"),
        "{out}"
    );
}
