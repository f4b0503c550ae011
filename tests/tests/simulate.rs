//! `nephele simulate` and `nephele bench scheduler` as a user runs them.

use nephele_tests::{nephele_err, nephele_ok};

#[test]
fn simulate_prints_the_table_and_writes_csv() {
    let dir = tempfile::tempdir().expect("tempdir");
    let csv = dir.path().join("table.csv");
    let users = dir.path().join("users.csv");
    let out = nephele_ok(&[
        "simulate",
        "--scenario",
        "straggler",
        "--duration",
        "1",
        "--policy",
        "nephele,round-robin",
        "--csv",
        csv.to_str().expect("utf-8"),
        "--users-csv",
        users.to_str().expect("utf-8"),
    ]);
    assert!(out.contains("attain%") && out.contains("nephele") && out.contains("round-robin"), "{out}");
    let table = std::fs::read_to_string(&csv).expect("csv written");
    let lines: Vec<&str> = table.lines().collect();
    assert_eq!(lines.len(), 3, "{table}");
    assert!(lines[0].starts_with("scenario,policy,users,admitted,refusals,attainment_mean"));
    assert!(lines[1].starts_with("straggler,nephele,6,6,0,"));
    let per_user = std::fs::read_to_string(&users).expect("users csv written");
    assert_eq!(per_user.lines().count(), 1 + 2 * 6);
    // Same seed, same numbers.
    let again = dir.path().join("again.csv");
    nephele_ok(&[
        "simulate",
        "--scenario",
        "straggler",
        "--duration",
        "1",
        "--policy",
        "nephele,round-robin",
        "--csv",
        again.to_str().expect("utf-8"),
    ]);
    assert_eq!(std::fs::read_to_string(&again).expect("csv"), table);
}

#[test]
fn simulate_replays_a_trace_and_rejects_malformed_ones() {
    let dir = tempfile::tempdir().expect("tempdir");
    let trace = dir.path().join("trace.csv");
    let farm = dir.path().join("farm.csv");
    std::fs::write(&trace, "# two users\nuser,arrive_s,depart_s,fps,width,height,fov_deg,views,objects,radius_m,height_m,speed_deg_s,start_deg\na,0,1,30,320,240,50,mono,cube:0:0:0:0.5,3,0.5,10,0\nb,0.2,1,30,320,240,50,quilt8,cube:0:0:0:0.5,3,0.5,0,45\n").expect("write");
    std::fs::write(&farm, "w1,5e7\nw2,5e7,0.1,0,0.5,drop\n").expect("write");
    let out = nephele_ok(&[
        "simulate",
        "--trace",
        trace.to_str().expect("utf-8"),
        "--workers",
        farm.to_str().expect("utf-8"),
        "--policy",
        "fifo",
    ]);
    assert!(out.contains("trace") && out.contains("fifo"), "{out}");
    std::fs::write(
        &trace,
        "a,0,1,30,320,240,50,mono,cube:0:0:0:0.5,3,0.5,10,0\nb,0,1,-5,320,240,50,mono,cube:0:0:0:0.5,3,0.5,10,0\n",
    )
    .expect("write");
    let err = nephele_err(&["simulate", "--trace", trace.to_str().expect("utf-8")]);
    assert!(err.contains("line 2") && err.contains("fps must be positive"), "{err}");
    std::fs::write(&farm, "w1,5e7\nw2,fast\n").expect("write");
    let err = nephele_err(&["simulate", "--scenario", "quilt", "--workers", farm.to_str().expect("utf-8")]);
    assert!(err.contains("line 2") && err.contains("rays_per_s 'fast'"), "{err}");
    assert!(nephele_err(&["simulate", "--scenario", "nope"]).contains("unknown scenario"));
    assert!(nephele_err(&["simulate", "--policy", "lottery"]).contains("unknown policy"));
    assert!(nephele_err(&["simulate", "--duration=-1"]).contains("--duration"));
}

#[test]
fn help_documents_the_formats_and_the_bench() {
    let help = nephele_ok(&["simulate", "--help"]);
    for needle in ["TRACE FORMAT", "FARM FORMAT", "arrive_s", "rays_per_s", "quilt", "jain"] {
        assert!(help.contains(needle), "--help lacks {needle}");
    }
    let list = nephele_ok(&["simulate", "--list"]);
    for name in ["many-objects", "many-users", "quilt", "overload", "worker-death", "straggler"] {
        assert!(list.contains(name), "{list}");
    }
    let bench = nephele_ok(&[
        "bench",
        "scheduler",
        "--users",
        "5",
        "--pending",
        "200",
        "--rounds",
        "5",
        "--workers",
        "4",
        "--policy",
        "nephele",
    ]);
    assert!(bench.contains("p50 us") && bench.contains("nephele"), "{bench}");
}
