//! The `esrp-dataset` command line, run as a real process.

use std::path::Path;
use std::process::{Command, Output};

pub(super) fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_esrp-dataset")).args(args).output().expect("the binary runs")
}

pub(super) fn text(output: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&output.stdout), String::from_utf8_lossy(&output.stderr))
}

fn files_in(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files: Vec<_> = std::fs::read_dir(dir.join("scenes"))
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap())
        })
        .collect();
    files.sort();
    files
}

#[test]
fn generate_validate_stats_and_show() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    let out = run(&["generate", "--out", a.to_str().unwrap(), "--scenes", "6", "--first", "10"]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("wrote 6 scenes"));
    // The same command gives byte-identical files, with one thread as with many.
    let out = run(&["generate", "--out", b.to_str().unwrap(), "--scenes", "6", "--first", "10", "--threads", "1"]);
    assert!(out.status.success(), "{}", text(&out));
    let files = files_in(&a);
    assert_eq!(files.len(), 6);
    assert_eq!(files, files_in(&b));
    // esrp-bench-v2 is the default.
    assert!(files[0].0.starts_with("esrp-bench-v2_00010"));
    // Refuses to overwrite without --force.
    let out = run(&["generate", "--out", a.to_str().unwrap(), "--scenes", "1"]);
    assert!(!out.status.success() && text(&out).contains("--force"), "{}", text(&out));

    let out = run(&["validate", a.to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("6 of 6 scenes valid"));
    assert!(text(&out).contains("start poses: "), "{}", text(&out));

    let stats = tmp.path().join("stats");
    let out = run(&["stats", a.to_str().unwrap(), "--out", stats.to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out));
    for plot in
        ["room_types.png", "categories.png", "difficulty.png", "clutter.png", "start_distance.png", "first_fetch.png"]
    {
        let bytes = std::fs::read(stats.join(plot)).unwrap();
        assert_eq!(&bytes[1..4], b"PNG", "{plot}");
    }
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(stats.join("stats.json")).unwrap()).unwrap();
    assert_eq!(json["scenes"], 6);
    // v2 starts away from the objects: the expert drives before its first fetch.
    assert!(json["mean_first_fetch"].as_f64().unwrap() > 0.0, "{json}");
    assert!(json["mean_start_distance"].as_f64().unwrap() > 1.0, "{json}");

    // `show` by id from the folder equals the file; by index it generates the same scene.
    let out = run(&["show", "esrp-bench-v2/00012", "--dataset", a.to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out));
    let shown = String::from_utf8(out.stdout).unwrap();
    let generated = run(&["show", "12"]);
    assert_eq!(shown, String::from_utf8(generated.stdout).unwrap());
    let file = std::fs::read_to_string(a.join("scenes/esrp-bench-v2_00012.json")).unwrap();
    assert_eq!(shown, file);
}

#[test]
fn esrp_bench_v1_stays_selectable() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("v1");
    let out = run(&["generate", "--benchmark", "esrp-bench-v1", "--out", dir.to_str().unwrap(), "--scenes", "2"]);
    assert!(out.status.success(), "{}", text(&out));
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["name"], "esrp-bench-v1");
    let file = std::fs::read_to_string(dir.join("scenes/esrp-bench-v1_00001.json")).unwrap();
    // A v1 id names its version; an index takes --benchmark.
    let by_id = run(&["show", "esrp-bench-v1/00001"]);
    assert_eq!(String::from_utf8(by_id.stdout).unwrap(), file);
    let by_index = run(&["show", "1", "--benchmark", "esrp-bench-v1"]);
    assert_eq!(String::from_utf8(by_index.stdout).unwrap(), file);
    let stats = tmp.path().join("stats");
    assert!(run(&["stats", dir.to_str().unwrap(), "--out", stats.to_str().unwrap()]).status.success());
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(stats.join("stats.json")).unwrap()).unwrap();
    assert_eq!(json["mean_first_fetch"], 0.0, "{json}");
    assert_eq!(json["starts_within_reach"], 2, "{json}");
    let out = run(&["validate", dir.to_str().unwrap()]);
    assert!(out.status.success() && text(&out).contains("2 of 2 scenes valid"), "{}", text(&out));
    let out = run(&["generate", "--benchmark", "esrp-bench-v3", "--out", dir.to_str().unwrap()]);
    assert!(!out.status.success() && text(&out).contains("unknown benchmark"), "{}", text(&out));
}

#[test]
fn validate_checks_the_v2_start_rule() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("d");
    assert!(run(&["generate", "--out", dir.to_str().unwrap(), "--scenes", "1", "--first", "3"]).status.success());
    // Scene 3 of v1 (the agent at the last release) under its v2 id: it replays, but starts
    // within reach of an object where the room has poses 1.5 m away.
    let v1 = run(&["show", "esrp-bench-v1/00003"]);
    let mut scene: serde_json::Value = serde_json::from_slice(&v1.stdout).unwrap();
    scene["id"] = serde_json::json!("esrp-bench-v2/00003");
    std::fs::write(dir.join("scenes/esrp-bench-v2_00003.json"), scene.to_string()).unwrap();
    let out = run(&["validate", dir.to_str().unwrap()]);
    let t = text(&out);
    assert!(!out.status.success() && t.contains("start pose") && t.contains("0 of 1 scenes valid"), "{t}");
}

#[test]
fn validate_reports_a_broken_scene_and_fails() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("d");
    assert!(run(&["generate", "--out", dir.to_str().unwrap(), "--scenes", "2"]).status.success());
    let path = dir.join("scenes/esrp-bench-v2_00001.json");
    let mut scene: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    scene["expert_trajectory"] = serde_json::json!([0, 1]);
    std::fs::write(&path, scene.to_string()).unwrap();
    let out = run(&["validate", dir.to_str().unwrap()]);
    assert!(!out.status.success());
    let t = text(&out);
    assert!(t.contains("esrp-bench-v2/00001") && t.contains("replay") && t.contains("1 of 2 scenes valid"), "{t}");
}

#[test]
fn validate_checks_the_horizon_rule() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("d");
    assert!(run(&["generate", "--out", dir.to_str().unwrap(), "--scenes", "2"]).status.success());
    let path = dir.join("scenes/esrp-bench-v2_00001.json");
    let mut scene: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let steps = scene["expert_trajectory"].as_array().unwrap().len();
    let rule = scene["horizon"].as_u64().unwrap();
    assert_eq!(rule, ((2 * steps as u64).div_ceil(50) * 50).max(200), "the generator keeps the rule");
    // Longer than the rule: the expert still replays, the scene is still refused.
    scene["horizon"] = serde_json::json!(rule + 50);
    std::fs::write(&path, scene.to_string()).unwrap();
    let out = run(&["validate", dir.to_str().unwrap()]);
    let t = text(&out);
    assert!(!out.status.success(), "{t}");
    let expected = format!("esrp-bench-v2/00001: horizon {} where the rule gives {rule}", rule + 50);
    assert!(t.contains(&expected) && t.contains("1 of 2 scenes valid"), "{t}");
}

#[test]
fn bad_arguments_get_clear_errors() {
    let out = run(&["generate", "--out", "/tmp/never-written", "--first", "99999"]);
    assert!(!out.status.success() && text(&out).contains("past the end"), "{}", text(&out));
    let out = run(&["show", "no-such-scene"]);
    assert!(!out.status.success() && text(&out).contains("is not a scene of esrp-bench-v2"), "{}", text(&out));
    let out = run(&["validate", "/nonexistent/dataset"]);
    assert!(!out.status.success() && text(&out).contains("manifest.json"), "{}", text(&out));
    // Counts of nothing are refused, not an empty dataset written.
    let tmp = tempfile::tempdir().unwrap();
    let empty = tmp.path().join("empty");
    let out = run(&["generate", "--out", empty.to_str().unwrap(), "--scenes", "0"]);
    assert!(!out.status.success() && text(&out).contains("must be at least 1"), "{}", text(&out));
    assert!(!empty.exists());
    let out = run(&["import-3dfront", "--front", "/tmp", "--future", "/tmp", "--out", "/tmp/x", "--max-houses", "0"]);
    assert!(!out.status.success() && text(&out).contains("must be at least 1"), "{}", text(&out));
}

#[test]
fn import_3dfront_writes_a_valid_dataset() {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/3dfront");
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("front");
    let out = run(&[
        "import-3dfront",
        "--front",
        fixtures.join("front").to_str().unwrap(),
        "--future",
        fixtures.join("future").to_str().unwrap(),
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    let t = text(&out);
    assert!(out.status.success(), "{t}");
    assert!(t.contains("imported 1 of 2 rooms") && t.contains("no_floor_mesh") && t.contains("warning"), "{t}");
    let out = run(&["validate", out_dir.to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out));
    // A folder without house files is an error that names it, and writes nothing.
    let empty = tmp.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let out_dir = tmp.path().join("never");
    let out = run(&[
        "import-3dfront",
        "--front",
        empty.to_str().unwrap(),
        "--future",
        fixtures.join("future").to_str().unwrap(),
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    assert!(!out.status.success() && text(&out).contains("empty"), "{}", text(&out));
    assert!(!out_dir.exists());
}

#[test]
fn validate_and_stats_report_each_fallback_start() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("d");
    // esrp-bench-v2/01909: after its last release the generator's agent is in a pocket of the
    // furniture whose farthest reachable pose is 0.73 m from an object (the search is not capped:
    // 152 positions on its finest grid), so the start is that pose, within fetch reach.
    assert!(run(&["generate", "--out", dir.to_str().unwrap(), "--scenes", "1", "--first", "1909"]).status.success());
    let out = run(&["validate", dir.to_str().unwrap()]);
    let t = text(&out);
    assert!(out.status.success() && t.contains("1 of 1 scenes valid"), "{t}");
    assert!(
        t.contains(
            "start poses: 0 of 1 at least 1.5 m from every object; 1 the farthest reachable (1 within fetch reach"
        ),
        "{t}"
    );
    assert!(t.contains("  esrp-bench-v2/01909: 0.729 m from the nearest object"), "{t}");
    let stats = tmp.path().join("stats");
    assert!(run(&["stats", dir.to_str().unwrap(), "--out", stats.to_str().unwrap()]).status.success());
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(stats.join("stats.json")).unwrap()).unwrap();
    let fallbacks = json["fallback_starts"].as_object().unwrap();
    assert_eq!(fallbacks.len(), 1, "{json}");
    let distance = fallbacks["esrp-bench-v2/01909"].as_f64().unwrap();
    assert!((distance - 0.729).abs() < 1e-3, "{json}");
}
