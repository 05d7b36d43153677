//! `esrp-dataset` on bad input and bad output paths: a clear error and a non-zero exit, found
//! before minutes of generation are spent, and a dataset that `validate` passes is one the
//! server reads as its scenes say.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use super::cli::{run, text};

/// Runs the binary, killing it if it is still running after `limit` (then `None`).
fn run_within(args: &[&str], limit: Duration) -> Option<Output> {
    let mut child = Command::new(env!("CARGO_BIN_EXE_esrp-dataset"))
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the binary runs");
    let started = Instant::now();
    while started.elapsed() < limit {
        if child.try_wait().unwrap().is_some() {
            return Some(child.wait_with_output().unwrap());
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    None
}

#[test]
fn an_unwritable_out_fails_once_before_generating() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("a-file");
    std::fs::write(&file, b"not a folder").unwrap();
    let out = file.join("dataset");
    let output = run(&["generate", "--out", out.to_str().unwrap(), "--scenes", "12", "--first", "20"]);
    let t = text(&output);
    assert_eq!(output.status.code(), Some(1), "{t}");
    // One error naming the folder, not one per scene after every scene was generated.
    assert_eq!(t.matches("error:").count(), 1, "{t}");
    assert!(t.contains("a-file") && !t.contains("wrote"), "{t}");
}

#[test]
fn a_range_past_every_index_is_an_error_not_a_panic() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    let output =
        run(&["generate", "--out", out.to_str().unwrap(), "--first", "1", "--scenes", &usize::MAX.to_string()]);
    let t = text(&output);
    assert_eq!(output.status.code(), Some(1), "{t}");
    assert!(t.contains("runs past") && !t.contains("panicked"), "{t}");
    assert!(!out.exists());
}

#[test]
fn an_io_error_is_said_once() {
    let output = run(&["validate", "/nonexistent/dataset"]);
    let t = text(&output);
    assert_eq!(output.status.code(), Some(1), "{t}");
    assert_eq!(t.matches("No such file or directory").count(), 1, "{t}");
}

#[test]
fn pack_check_reads_the_pack_before_generating_the_benchmark() {
    // Generating the whole benchmark takes minutes: each of these is answered at once.
    let tmp = tempfile::tempdir().unwrap();
    let limit = Duration::from_secs(30);
    let missing = tmp.path().join("missing.pack");
    let output = run_within(&["pack", "--check", "--out", missing.to_str().unwrap()], limit)
        .expect("a missing pack is reported before the benchmark is generated");
    assert!(!output.status.success() && text(&output).contains("missing.pack"), "{}", text(&output));

    let garbage = tmp.path().join("garbage.pack");
    std::fs::write(&garbage, b"hello").unwrap();
    let output = run_within(&["pack", "--check", "--out", garbage.to_str().unwrap()], limit)
        .expect("a file that is no pack is reported before the benchmark is generated");
    assert!(!output.status.success() && text(&output).contains("not a scene pack"), "{}", text(&output));

    // A pack of another seed (one empty scene list under its header).
    let other = tmp.path().join("other.pack");
    std::fs::write(
        &other,
        b"esrp-scene-pack/v1\n{\"benchmark\":\"esrp-bench-v2\",\"seed\":9,\"generator\":\"x\",\"count\":0}\n",
    )
    .unwrap();
    let output = run_within(&["pack", "--check", "--out", other.to_str().unwrap()], limit)
        .expect("a pack of another benchmark is reported before the benchmark is generated");
    assert!(
        !output.status.success() && text(&output).contains("not every scene of esrp-bench-v2"),
        "{}",
        text(&output)
    );

    // Writing into a path whose folder cannot be made: refused before generating.
    let blocked = garbage.join("esrp-bench-v2.pack");
    let output = run_within(&["pack", "--out", blocked.to_str().unwrap()], limit)
        .expect("an unwritable --out is reported before the benchmark is generated");
    assert!(!output.status.success() && text(&output).contains("garbage.pack"), "{}", text(&output));
}

fn manifest(dir: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap()
}

fn set_manifest(dir: &Path, manifest: &serde_json::Value) {
    std::fs::write(dir.join("manifest.json"), manifest.to_string()).unwrap();
}

#[test]
fn validate_checks_the_manifest_against_the_scenes() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("d");
    assert!(run(&["generate", "--out", dir.to_str().unwrap(), "--scenes", "2", "--first", "30"]).status.success());
    let original = manifest(&dir);

    // The server serves a scene under the manifest's split: a manifest that says otherwise fails.
    let mut changed = original.clone();
    let split = changed["scenes"][1]["split"].as_str().unwrap().to_owned();
    let other = if split == "train" { "test" } else { "train" };
    changed["scenes"][1]["split"] = serde_json::json!(other);
    set_manifest(&dir, &changed);
    let output = run(&["validate", dir.to_str().unwrap()]);
    let t = text(&output);
    assert!(!output.status.success() && t.contains("1 of 2 scenes valid"), "{t}");
    assert!(t.contains(&format!("esrp-bench-v2/00031: the manifest says split {other}, the file {split}")), "{t}");

    // One scene listed twice.
    let mut changed = original.clone();
    let first = changed["scenes"][0].clone();
    changed["scenes"][1] = first;
    set_manifest(&dir, &changed);
    let output = run(&["validate", dir.to_str().unwrap()]);
    let t = text(&output);
    assert!(!output.status.success() && t.contains("esrp-bench-v2/00030: listed 2 times in the manifest"), "{t}");

    // No scenes at all.
    let mut changed = original.clone();
    changed["scenes"] = serde_json::json!([]);
    set_manifest(&dir, &changed);
    let output = run(&["validate", dir.to_str().unwrap()]);
    let t = text(&output);
    assert!(!output.status.success() && t.contains("holds no scenes"), "{t}");

    set_manifest(&dir, &original);
    assert!(run(&["validate", dir.to_str().unwrap()]).status.success());
}

#[test]
fn an_import_that_imports_no_room_fails_and_writes_nothing() {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/3dfront");
    let tmp = tempfile::tempdir().unwrap();
    let front = tmp.path().join("front");
    std::fs::create_dir_all(&front).unwrap();
    let house_file = "0a1b2c3d-0000-4000-8000-000000000001.json";
    let mut house: serde_json::Value =
        serde_json::from_slice(&std::fs::read(fixtures.join("front").join(house_file)).unwrap()).unwrap();
    // Only the fixture's room without a floor mesh, which is skipped.
    let rooms = house["scene"]["room"].as_array_mut().unwrap();
    rooms.remove(0);
    std::fs::write(front.join(house_file), house.to_string()).unwrap();
    let out = tmp.path().join("out");
    let output = run(&[
        "import-3dfront",
        "--front",
        front.to_str().unwrap(),
        "--future",
        fixtures.join("future").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let t = text(&output);
    assert_eq!(output.status.code(), Some(1), "{t}");
    assert!(t.contains("no room") && t.contains("no_floor_mesh"), "{t}");
    assert!(!out.exists(), "{t}");
}
