//! The on-disk dataset format: `DIR/manifest.json` plus one `esrp.scene/v1` JSON file per
//! scene under `DIR/scenes/`. Every file is written to a temporary name and renamed into place,
//! so a crash never leaves a half-written file, and the manifest is written last.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use esrp_core::Scene;
use serde::{Deserialize, Serialize};

/// The manifest's schema string.
pub const MANIFEST_SCHEMA: &str = "esrp.dataset/v1";

/// One scene's entry in the manifest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ManifestEntry {
    /// Scene id.
    pub id: String,
    /// File name under `scenes/`.
    pub file: String,
    /// 3D-FRONT room type.
    pub room_type: String,
    /// `easy` / `medium` / `hard`.
    pub difficulty: esrp_core::Difficulty,
    /// `train` / `test`.
    pub split: esrp_core::Split,
    /// Number of movable objects.
    pub movable_objects: usize,
    /// Length of the expert trajectory.
    pub expert_length: usize,
}

/// `DIR/manifest.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`MANIFEST_SCHEMA`].
    pub schema: String,
    /// Dataset name, e.g. `esrp-bench-v1`.
    pub name: String,
    /// Generator and version that wrote it.
    pub generator: String,
    /// Seed of a generated dataset.
    #[serde(default)]
    pub seed: Option<u64>,
    /// Rejected generation attempts by reason.
    #[serde(default)]
    pub rejections: BTreeMap<String, usize>,
    /// The scenes, in order.
    pub scenes: Vec<ManifestEntry>,
}

/// A problem reading or writing dataset files.
#[derive(Debug, thiserror::Error)]
pub enum FilesError {
    /// An I/O error on a path.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// A file is not valid JSON of the expected shape.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> FilesError + '_ {
    move |source| FilesError::Io { path: path.to_owned(), source }
}

/// Writes `bytes` to `path` atomically: a temporary file beside it, flushed, then renamed.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FilesError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(io_error(dir))?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    // Unique per write: two threads (or processes) writing the same file never share a
    // temporary; the last rename wins, and each rename puts a whole file in place.
    static WRITES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = WRITES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.tmp-{}-{n}", std::process::id()));
    let mut file = std::fs::File::create(&tmp).map_err(io_error(&tmp))?;
    file.write_all(bytes).and_then(|()| file.sync_all()).map_err(io_error(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io_error(path))
}

/// Removes the temporary files that [`write_atomic`] left in `dir` in processes that are gone (a
/// run stopped by a signal between a write and its rename): `.NAME.tmp-PID-N` whose process `PID`
/// no longer runs. Returns how many it removed. Only where a process's liveness can be read
/// (`/proc`, Linux); elsewhere none.
pub fn remove_stale_temporaries(dir: &Path) -> usize {
    if !Path::new("/proc/self").exists() {
        return 0;
    }
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name.to_str().and_then(temporary_writer) else { continue };
        if pid != std::process::id()
            && !Path::new(&format!("/proc/{pid}")).exists()
            && std::fs::remove_file(entry.path()).is_ok()
        {
            removed += 1;
        }
    }
    removed
}

/// The process that wrote the temporary file `name` (`.NAME.tmp-PID-N`), if it is one.
fn temporary_writer(name: &str) -> Option<u32> {
    let rest = name.strip_prefix('.')?;
    let (_, tail) = rest.rsplit_once(".tmp-")?;
    let (pid, n) = tail.split_once('-')?;
    n.parse::<u64>().ok()?;
    pid.parse().ok()
}

/// The file name of a scene: its id with every character outside `[A-Za-z0-9._-]` replaced by
/// `_`, plus `.json` (`esrp-bench-v1/00042` → `esrp-bench-v1_00042.json`).
pub fn scene_file_name(id: &str) -> String {
    let safe: String =
        id.chars().map(|c| if c.is_ascii_alphanumeric() || "._-".contains(c) { c } else { '_' }).collect();
    format!("{safe}.json")
}

/// Writes one scene under `dir/scenes/` and returns its manifest entry.
pub fn write_scene(dir: &Path, scene: &Scene) -> Result<ManifestEntry, FilesError> {
    let file = scene_file_name(&scene.id);
    let mut text = scene.to_json_pretty();
    text.push('\n');
    write_atomic(&dir.join("scenes").join(&file), text.as_bytes())?;
    Ok(ManifestEntry {
        id: scene.id.clone(),
        file,
        room_type: scene.room_type.clone(),
        difficulty: scene.difficulty,
        split: scene.split,
        movable_objects: scene.movable_objects.len(),
        expert_length: scene.expert_trajectory.len(),
    })
}

/// Writes the manifest (last, after every scene file).
pub fn write_manifest(dir: &Path, manifest: &Manifest) -> Result<(), FilesError> {
    let mut text = serde_json::to_string_pretty(manifest).unwrap_or_default();
    text.push('\n');
    write_atomic(&dir.join("manifest.json"), text.as_bytes())
}

/// A dataset on disk.
#[derive(Clone, Debug)]
pub struct Dataset {
    dir: PathBuf,
    manifest: Manifest,
}

impl Dataset {
    /// Opens `dir` by reading its manifest.
    pub fn open(dir: &Path) -> Result<Self, FilesError> {
        let path = dir.join("manifest.json");
        let text = std::fs::read_to_string(&path).map_err(io_error(&path))?;
        let manifest: Manifest = serde_json::from_str(&text)
            .map_err(|e| FilesError::Parse { path: path.clone(), message: e.to_string() })?;
        if manifest.schema != MANIFEST_SCHEMA {
            return Err(FilesError::Parse {
                path,
                message: format!("unknown manifest schema {:?}: expected {MANIFEST_SCHEMA:?}", manifest.schema),
            });
        }
        Ok(Self { dir: dir.to_owned(), manifest })
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Reads the scene of one manifest entry.
    pub fn read_scene(&self, entry: &ManifestEntry) -> Result<Scene, FilesError> {
        let path = self.dir.join("scenes").join(&entry.file);
        let text = std::fs::read_to_string(&path).map_err(io_error(&path))?;
        Scene::from_json(&text).map_err(|e| FilesError::Parse { path, message: e.to_string() })
    }

    /// Reads the scene with id `id`, if the manifest lists it.
    pub fn scene_by_id(&self, id: &str) -> Option<Result<Scene, FilesError>> {
        self.manifest.scenes.iter().find(|e| e.id == id).map(|e| self.read_scene(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_are_safe() {
        assert_eq!(scene_file_name("esrp-bench-v1/00042"), "esrp-bench-v1_00042.json");
        assert_eq!(scene_file_name("3dfront/a b/../c"), "3dfront_a_b_.._c.json");
    }

    #[test]
    fn a_gone_writers_temporaries_are_removed_and_nothing_else() {
        assert_eq!(temporary_writer(".esrp_00001.json.tmp-4242-7"), Some(4242));
        assert_eq!(temporary_writer("esrp_00001.json"), None);
        assert_eq!(temporary_writer(".hidden"), None);
        assert_eq!(temporary_writer(".a.tmp-x-1"), None);
        if !Path::new("/proc/self").exists() {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        // A process id that runs no process: past the kernel's limit (4,194,304 at most).
        let gone = dir.path().join(".s.json.tmp-4194305-0");
        let mine = dir.path().join(format!(".s.json.tmp-{}-0", std::process::id()));
        let kept = [dir.path().join("s.json"), dir.path().join(".notes"), mine];
        for path in kept.iter().chain([&gone]) {
            std::fs::write(path, b"{}").unwrap();
        }
        assert_eq!(remove_stale_temporaries(dir.path()), 1);
        assert!(!gone.exists());
        assert!(kept.iter().all(|p| p.exists()));
    }
}
