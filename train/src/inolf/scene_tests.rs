//! Perfect spatial hashes of every built-in scene's surface voxels.

use nephele_kernels::inolf::psh::{PshOptions, PshTable, pack_key};
use nephele_pathtracer::scenes;
use nephele_pathtracer::voxel::{VoxelGrid, surface_voxels};

/// Zero collisions on every built-in scene at 128^3 (proved by checking that every
/// occupied voxel gets its own slot and holds its own key), and the coherence the
/// construction achieves on real surfaces.
#[test]
fn builtin_scenes_hash_perfectly_and_coherently() {
    for name in scenes::names() {
        let builtin = scenes::builtin(name).expect("builtin");
        let (lo, hi) = builtin.scene.bounds().expect("bounds");
        let grid = VoxelGrid::around(lo, hi, 128);
        let points = surface_voxels(&builtin.scene.mesh, &grid);
        assert!(!points.is_empty(), "{name}: no surface voxels");
        for (label, options, floor) in
            [("paper", PshOptions::default(), 0.01), ("coherent", PshOptions::coherent(), 0.3)]
        {
            let (table, stats) = PshTable::build(128, &points, &options).expect("build");
            let mut seen = vec![false; table.slot_count()];
            for &p in &points {
                let s = table.slot(p).unwrap_or_else(|| panic!("{name}: voxel {p:?} not found")) as usize;
                assert!(!seen[s], "{name}: collision at slot {s}");
                seen[s] = true;
            }
            assert_eq!(table.len(), points.len());
            // Unoccupied voxels next to the surface are rejected.
            for &p in points.iter().step_by(7) {
                for q in [[p[0] + 1, p[1], p[2]], [p[0], p[1] + 1, p[2]], [p[0], p[1], p[2] + 1]] {
                    if points.binary_search_by_key(&pack_key(q), |&v| pack_key(v)).is_err() {
                        assert_eq!(table.slot(q), None, "{name}: unoccupied {q:?} accepted");
                    }
                }
            }
            let (coherent, pairs) = table.coherence();
            let fraction = coherent as f64 / pairs.max(1) as f64;
            eprintln!(
                "{name:<11} {label:<8} n = {:>7}  m = {:>3}  r = {:>3}  attempts {}  coherence {fraction:.3} ({coherent}/{pairs})",
                points.len(),
                table.table_side(),
                table.offset_side(),
                stats.attempts
            );
            assert!(fraction > floor, "{name} {label}: coherence {fraction}");
        }
    }
}
