//! A built-in benchmark's generated scenes kept on disk, so that each is generated once per
//! machine rather than once per server start.
//!
//! The cache of a benchmark lives in `ROOT/<benchmark name>/seed-<seed>/generator-<version>/`,
//! where `<version>` is [`GENERATOR_VERSION`]: a scene is found again only by the generator that
//! made it. Each scene is one file, `NNNNN.scene`: a header line `esrp-scene-cache/v1 <sha256>`
//! and the scene's JSON, whose SHA-256 the header gives. Files are written atomically (a
//! temporary file, synced, then renamed), so readers and concurrent writers — several servers
//! sharing a cache, a server's request path and its background generation — see whole files or
//! none. A file that does not check out (cut short, edited, another format) is reported as
//! [`Lookup::Corrupt`]: the caller generates the scene again and overwrites it.
//!
//! Scenes read back are equal to the generated ones (`serde_json` reads floats back exactly).

use std::path::{Path, PathBuf};

use esrp_core::Scene;
use sha2::{Digest, Sha256};

use crate::benchmark::Benchmark;
use crate::files::{FilesError, write_atomic};

/// The generator's version in cache keys: the package version and a revision that changes
/// whenever any generated scene would (a published benchmark never does; a test pins them).
pub const GENERATOR_VERSION: &str = concat!(env!("CARGO_PKG_VERSION"), "-r1");

/// The first word of a cache file's header.
const HEADER: &str = "esrp-scene-cache/v1";

/// The default cache root: `$XDG_CACHE_HOME/esrp/scenes`, else `$HOME/.cache/esrp/scenes`;
/// `None` when neither is set.
pub fn default_root() -> Option<PathBuf> {
    let base = std::env::var_os("XDG_CACHE_HOME")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").filter(|v| !v.is_empty()).map(|h| PathBuf::from(h).join(".cache")))?;
    Some(base.join("esrp").join("scenes"))
}

/// What the cache holds for a scene.
#[derive(Debug)]
pub enum Lookup {
    /// The scene, checked.
    Hit(Box<Scene>),
    /// Nothing yet.
    Miss,
    /// A file that does not check out; why.
    Corrupt(String),
}

/// One benchmark's scenes on disk.
#[derive(Clone, Debug)]
pub struct SceneCache {
    dir: PathBuf,
}

impl SceneCache {
    /// The cache of `bench` under `root`, its folder created if missing.
    pub fn open(root: &Path, bench: &Benchmark) -> Result<Self, FilesError> {
        let dir = root
            .join(bench.name())
            .join(format!("seed-{}", bench.seed()))
            .join(format!("generator-{GENERATOR_VERSION}"));
        std::fs::create_dir_all(&dir).map_err(|source| FilesError::Io { path: dir.clone(), source })?;
        Ok(Self { dir })
    }

    /// Its folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn path(&self, index: usize) -> PathBuf {
        self.dir.join(format!("{index:05}.scene"))
    }

    /// Whether scene `index` has a file (not checked).
    pub fn contains(&self, index: usize) -> bool {
        self.path(index).is_file()
    }

    /// Scene `index`, if a file holds it whole.
    pub fn get(&self, index: usize) -> Lookup {
        let path = self.path(index);
        let bytes = match std::fs::read(&path) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Lookup::Miss,
            Err(e) => return Lookup::Corrupt(format!("{}: {e}", path.display())),
        };
        match check(&bytes) {
            Ok(scene) => Lookup::Hit(Box::new(scene)),
            Err(why) => Lookup::Corrupt(format!("{}: {why}", path.display())),
        }
    }

    /// Keeps `scene` as scene `index` (replacing any file).
    pub fn put(&self, index: usize, scene: &Scene) -> Result<(), FilesError> {
        let json = serde_json::to_string(scene).unwrap_or_default();
        let text = format!("{HEADER} {}\n{json}", hex(&Sha256::digest(json.as_bytes())));
        write_atomic(&self.path(index), text.as_bytes())
    }
}

/// The scene of a cache file's bytes, or why they are not one.
fn check(bytes: &[u8]) -> Result<Scene, String> {
    let text = std::str::from_utf8(bytes).map_err(|_| "not UTF-8".to_owned())?;
    let (header, json) = text.split_once('\n').ok_or("no header line")?;
    let digest = header.strip_prefix(HEADER).and_then(|rest| rest.strip_prefix(' ')).ok_or("not a scene cache file")?;
    if hex(&Sha256::digest(json.as_bytes())) != digest {
        return Err("its checksum does not match (cut short or changed)".into());
    }
    Scene::from_json(json).map_err(|e| e.to_string())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::benchmark::{BenchVersion, DEFAULT_SEED};

    #[test]
    fn scenes_come_back_equal_and_damage_is_found() {
        let root = tempfile::tempdir().unwrap();
        let bench = Benchmark::new(BenchVersion::V2, DEFAULT_SEED);
        let cache = SceneCache::open(root.path(), &bench).unwrap();
        assert!(cache.dir().ends_with(format!("esrp-bench-v2/seed-0/generator-{GENERATOR_VERSION}")));
        assert!(matches!(cache.get(3), Lookup::Miss));
        for index in [0, 3, 17] {
            let scene = bench.generate(index).unwrap().scene;
            cache.put(index, &scene).unwrap();
            assert!(cache.contains(index));
            match cache.get(index) {
                Lookup::Hit(back) => assert_eq!(*back, scene, "scene {index} read back"),
                other => panic!("scene {index}: {other:?}"),
            }
        }
        // Cut short, one byte changed, or another file: each is found, never served.
        let path = cache.path(3);
        let whole = std::fs::read(&path).unwrap();
        std::fs::write(&path, &whole[..whole.len() / 2]).unwrap();
        assert!(matches!(cache.get(3), Lookup::Corrupt(why) if why.contains("checksum")));
        let mut changed = whole.clone();
        let last = changed.len() - 2;
        changed[last] = if changed[last] == b'1' { b'2' } else { b'1' };
        std::fs::write(&path, &changed).unwrap();
        assert!(matches!(cache.get(3), Lookup::Corrupt(_)));
        std::fs::write(&path, "{}").unwrap();
        assert!(matches!(cache.get(3), Lookup::Corrupt(why) if why.contains("no header")));
        // Writing again repairs it; no temporary file stays behind.
        cache.put(3, &bench.generate(3).unwrap().scene).unwrap();
        assert!(matches!(cache.get(3), Lookup::Hit(_)));
        let names: Vec<String> =
            std::fs::read_dir(cache.dir()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into()).collect();
        assert!(names.iter().all(|n| n.ends_with(".scene")), "{names:?}");
    }

    #[test]
    fn other_seeds_and_versions_have_their_own_folders() {
        let root = tempfile::tempdir().unwrap();
        let a = SceneCache::open(root.path(), &Benchmark::new(BenchVersion::V2, 0)).unwrap();
        let b = SceneCache::open(root.path(), &Benchmark::new(BenchVersion::V2, 1)).unwrap();
        let c = SceneCache::open(root.path(), &Benchmark::new(BenchVersion::V1, 0)).unwrap();
        assert_ne!(a.dir(), b.dir());
        assert_ne!(a.dir(), c.dir());
    }
}
