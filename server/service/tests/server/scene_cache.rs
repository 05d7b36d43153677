//! The built-in benchmark's scene cache on disk (`--scene-cache`), for the benchmarks the server
//! has no pack of (esrp-bench-v1 here): a scene served from the cache is the generated one, a
//! damaged entry is generated again and repaired, and the background generation fills the cache,
//! test split first. The default benchmark is served from the pack built into the server: it
//! writes no scene to the cache and generates none ahead.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use esrp_dataset::cache::{GENERATOR_VERSION, Lookup, SceneCache};
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED};
use esrp_server::proto;

use super::harness::{Server, create_request};

const SCENE: &str = "esrp-bench-v1/00003";

/// The flags of a server of the benchmark without a pack.
const V1: [&str; 2] = ["--benchmark", "esrp-bench-v1"];

/// The scene JSON a privileged episode of `SCENE` shows.
async fn served_scene(server: &Server) -> String {
    let mut client = server.client().await;
    let created = client.create_episode(create_request(SCENE, true)).await.unwrap().into_inner();
    let state = client
        .get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: created.episode_id })
        .await
        .unwrap()
        .into_inner();
    state.scene_json
}

fn cache_dir(root: &Path) -> PathBuf {
    root.join("esrp-bench-v1").join("seed-0").join(format!("generator-{GENERATOR_VERSION}"))
}

fn entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map(|d| d.filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).collect())
        .unwrap_or_default();
    names.sort();
    names
}

#[tokio::test]
async fn cached_scenes_are_the_generated_ones_and_damage_is_repaired() {
    let root = tempfile::tempdir().unwrap();
    let cache = root.path().to_str().unwrap();
    let uncached = served_scene(&Server::start(&[&V1[..], &["--no-scene-cache"]].concat())).await;
    // First use: generated and kept (and only that scene: nothing is generated ahead here).
    let with_cache = [&V1[..], &["--scene-cache", cache]].concat();
    let first = served_scene(&Server::start(&with_cache)).await;
    assert_eq!(first, uncached);
    let dir = cache_dir(root.path());
    assert_eq!(entries(&dir), ["00003.scene"]);
    // A later server reads it back: the same scene.
    let again = served_scene(&Server::start(&with_cache)).await;
    assert_eq!(again, uncached);
    // A damaged entry is never served: the scene is generated again, and the entry repaired.
    let path = dir.join("00003.scene");
    let whole = std::fs::read(&path).unwrap();
    std::fs::write(&path, &whole[..whole.len() - 40]).unwrap();
    let repaired = served_scene(&Server::start(&with_cache)).await;
    assert_eq!(repaired, uncached);
    assert_eq!(std::fs::read(&path).unwrap(), whole);
}

#[tokio::test]
async fn missing_scenes_are_generated_ahead_test_split_first() {
    let root = tempfile::tempdir().unwrap();
    // The same variable as the harness's default, set to false: generate ahead.
    let _server = Server::start_with_env(
        &[&V1[..], &["--scene-cache", root.path().to_str().unwrap()]].concat(),
        &[("ESRP_NO_GENERATE_AHEAD", "false")],
    );
    let dir = cache_dir(root.path());
    // The thread runs only on idle cores: give it time on a busy test machine.
    let deadline = Instant::now() + Duration::from_secs(300);
    while entries(&dir).iter().filter(|n| n.ends_with(".scene")).count() < 3 {
        assert!(Instant::now() < deadline, "no scenes generated ahead in 300 s: {:?}", entries(&dir));
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let bench = Benchmark::new(BenchVersion::V1, DEFAULT_SEED);
    let cache = SceneCache::open(root.path(), &bench).unwrap();
    for name in entries(&dir).iter().filter(|n| n.ends_with(".scene")) {
        let index: usize = name.trim_end_matches(".scene").parse().unwrap();
        assert_eq!(bench.split(index), esrp_core::Split::Test, "{name}: the test split comes first");
        match cache.get(index) {
            Lookup::Hit(scene) => assert_eq!(*scene, bench.generate(index).unwrap().scene, "{name}"),
            other => panic!("{name}: {other:?}"),
        }
    }
}

/// The default benchmark comes from the pack built into the server: the same scene as generated,
/// with nothing written to the scene cache and nothing generated ahead.
#[tokio::test]
async fn the_default_benchmark_is_served_from_the_built_in_pack() {
    let root = tempfile::tempdir().unwrap();
    let server = Server::start_with_env(
        &["--scene-cache", root.path().to_str().unwrap()],
        &[("ESRP_NO_GENERATE_AHEAD", "false")],
    );
    let mut client = server.client().await;
    let created = client.create_episode(create_request("esrp-bench-v2/00003", true)).await.unwrap().into_inner();
    let state = client
        .get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: created.episode_id })
        .await
        .unwrap()
        .into_inner();
    let generated = Benchmark::new(BenchVersion::V2, DEFAULT_SEED).generate(3).unwrap().scene;
    assert_eq!(esrp_core::Scene::from_json(&state.scene_json).unwrap(), generated);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let dir = root.path().join("esrp-bench-v2").join("seed-0").join(format!("generator-{GENERATOR_VERSION}"));
    assert!(entries(&dir).iter().all(|n| !n.ends_with(".scene")), "{:?}", entries(&dir));
}
