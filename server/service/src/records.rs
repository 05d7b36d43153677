//! The server keeps the score: its own `esrp.results/v1` record of every episode played on the
//! challenge split (`--records DIR`; every episode with `--record all`), appended to
//! `DIR/<token-name>.jsonl`, and the rule of one counted attempt per challenge scene and token.
//!
//! Durability: a record is written and `fsync`ed by the recorder's thread before the answer to
//! the step that ended its episode (or the close that ended it) is sent, so a `kill -9` loses
//! at most the records of episodes still running. Records that end at once are written
//! together and share one `fsync` per file (a group commit). At start the files are read back:
//! a last line torn by a crash is cut off, and the counted attempts are known again.

use std::collections::HashMap;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use esrp_results::EpisodeRecord;

use crate::quote::quoted;
use crate::types::Caller;

/// Which episodes the server records.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum RecordMode {
    /// Episodes on the challenge split.
    Challenge,
    /// Every episode, on any split, by any token.
    All,
}

impl RecordMode {
    /// `challenge` or `all`.
    pub fn as_str(self) -> &'static str {
        match self {
            RecordMode::Challenge => "challenge",
            RecordMode::All => "all",
        }
    }
}

/// RFC 3339 UTC time, seconds.
pub fn rfc3339(time: SystemTime) -> String {
    humantime::format_rfc3339_seconds(time).to_string()
}

/// The state of one token's attempt at one challenge scene.
#[derive(Clone, Debug)]
enum Attempt {
    /// Created at this time, not ended yet.
    Running(String),
    /// Ended (and recorded) at this time.
    Ended(String),
}

/// A second attempt at a challenge scene: the token's one counted attempt there is taken.
#[derive(Clone, Debug, thiserror::Error)]
#[error(
    "challenge scene {} was already played by {caller} ({when}): each token gets one counted attempt per challenge scene (the minival split may be played again)",
    quoted(.scene)
)]
pub struct AlreadyPlayed {
    /// The scene.
    pub scene: String,
    /// The caller, described.
    pub caller: String,
    /// When: `ended 2026-11-25T20:00:00Z` or `started …, still running`.
    pub when: String,
}

/// The counted attempts: one per challenge scene and token (admins are not counted).
#[derive(Default)]
pub struct Attempts {
    taken: Mutex<HashMap<(Arc<str>, String), Attempt>>,
}

impl Attempts {
    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<(Arc<str>, String), Attempt>> {
        self.taken.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Takes `caller`'s attempt at challenge scene `scene`, or says when it was taken.
    pub fn take(&self, caller: &Caller, scene: &str) -> Result<(), AlreadyPlayed> {
        let mut map = self.map();
        let key = (caller.name.clone(), scene.to_owned());
        if let Some(attempt) = map.get(&key) {
            let when = match attempt {
                Attempt::Running(at) => format!("started {at}, still running"),
                Attempt::Ended(at) => format!("ended {at}"),
            };
            return Err(AlreadyPlayed { scene: scene.to_owned(), caller: caller.describe(), when });
        }
        map.insert(key, Attempt::Running(rfc3339(SystemTime::now())));
        Ok(())
    }

    /// Gives an attempt back: its episode never reached its client (an abandoned create).
    pub fn give_back(&self, token: &Arc<str>, scene: &str) {
        self.map().remove(&(token.clone(), scene.to_owned()));
    }

    /// Marks an attempt ended at `at`.
    pub fn ended(&self, token: &str, scene: &str, at: &str) {
        self.map().insert((token.into(), scene.to_owned()), Attempt::Ended(at.to_owned()));
    }

    /// Whether `token`'s attempt at `scene` has ended (and been recorded).
    pub fn is_ended(&self, token: &str, scene: &str) -> bool {
        matches!(self.map().get(&(token.into(), scene.to_owned())), Some(Attempt::Ended(_)))
    }

    /// The number of attempts known.
    pub fn len(&self) -> usize {
        self.map().len()
    }

    /// Whether no attempt is known.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The key the server signs its records with: HMAC-SHA256 over each record's line without its
/// `signature` member, so that a record the server wrote can be told from any other
/// (`esrp verify --key`). The key is the file's bytes, surrounding whitespace left out.
#[derive(Clone)]
pub struct RecordsKey(Vec<u8>);

/// The key file the server generates in its records folder when `--records-key` is not given.
pub const GENERATED_KEY: &str = "records.key";

impl std::fmt::Debug for RecordsKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RecordsKey(..)")
    }
}

impl RecordsKey {
    /// Reads the key of `given` (`--records-key FILE`), or of `DIR/records.key`, generating that
    /// one (32 random bytes as 64 hex digits, readable by its owner only) if it does not exist.
    pub fn load_or_create(dir: &Path, given: Option<&Path>) -> Result<Self, RecordsError> {
        let error = |reason: String| RecordsError { dir: dir.display().to_string(), reason };
        let path = given.map(Path::to_path_buf).unwrap_or_else(|| dir.join(GENERATED_KEY));
        if given.is_none() && !path.exists() {
            let mut random = uuid::Uuid::new_v4().as_bytes().to_vec();
            random.extend_from_slice(uuid::Uuid::new_v4().as_bytes());
            write_atomically(&path, hex::encode(&random).as_bytes(), 0o600)
                .map_err(|e| error(format!("cannot write the records key {}: {e}", path.display())))?;
            tracing::info!(file = %path.display(), "generated the key the records are signed with");
        }
        let bytes =
            std::fs::read(&path).map_err(|e| error(format!("cannot read the records key {}: {e}", path.display())))?;
        let key = bytes.trim_ascii();
        if key.len() < 16 {
            return Err(error(format!(
                "the records key {} holds {} bytes: give at least 16 (e.g. `openssl rand -hex 32`)",
                path.display(),
                key.len()
            )));
        }
        Ok(Self(key.to_vec()))
    }

    /// The key `bytes` (tests, tools).
    pub fn from_bytes(bytes: &[u8]) -> Self {
        Self(bytes.to_vec())
    }

    /// `json` (a record's compact JSON, without a signature) with `,"signature":"<hex>"` added
    /// as its last member: the HMAC-SHA256 of `json` as given.
    pub fn sign(&self, json: &[u8]) -> Vec<u8> {
        use hmac::{KeyInit, Mac};
        let mut mac = hmac::Hmac::<sha2::Sha256>::new_from_slice(&self.0).expect("HMAC takes a key of any length");
        mac.update(json);
        let signature = hex::encode(mac.finalize().into_bytes());
        let mut line = json.strip_suffix(b"}").unwrap_or(json).to_vec();
        line.extend_from_slice(format!(",\"signature\":\"{signature}\"}}").as_bytes());
        line
    }

    /// Whether `line` (without its newline) ends with a signature of the rest by this key.
    pub fn verify(&self, line: &[u8]) -> bool {
        const TAIL: usize = r#","signature":""}"#.len() + 64;
        if line.len() < TAIL || !line[line.len() - TAIL..].starts_with(br#","signature":""#) {
            return false;
        }
        let mut signed = line[..line.len() - TAIL].to_vec();
        signed.push(b'}');
        subtle::ConstantTimeEq::ct_eq(self.sign(&signed).as_slice(), line).into()
    }
}

/// The attempts journal, in the records folder: a line per counted attempt claimed (synced
/// before its episode exists) and per action it took (synced within milliseconds), so that an
/// attempt a crash cut still counts and is recorded at its last journaled step.
pub const JOURNAL: &str = "attempts.journal";

/// A counted attempt, as journaled when it is claimed.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Claim {
    /// The token.
    pub token: String,
    /// The challenge scene.
    pub scene: String,
    /// The agent label its create gave.
    pub agent: String,
    /// RFC 3339 UTC time of the claim.
    pub started_at: String,
    /// The episode's settings (horizon, reward weights), for a replay of its journaled actions.
    #[serde(default)]
    pub config: esrp_core::EpisodeConfig,
}

/// A line of the attempts journal.
#[derive(Debug, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
enum JournalLine {
    Claim(Claim),
    Step {
        token: String,
        scene: String,
        action: u8,
    },
    /// The attempt was given back (its create was abandoned before any use).
    Release {
        token: String,
        scene: String,
    },
}

/// A claimed attempt read back from the journal, with its journaled actions in order.
#[derive(Debug, PartialEq)]
pub struct Journaled {
    /// The claim.
    pub claim: Claim,
    /// Its actions.
    pub actions: Vec<u8>,
}

/// The attempts journaled in folder `dir` (none if it has no journal), in claim order. A last
/// line torn by a crash is cut off the file; an unreadable line elsewhere is an error.
pub fn read_journal(dir: &Path) -> Result<Vec<Journaled>, RecordsError> {
    let error = |reason: String| RecordsError { dir: dir.display().to_string(), reason };
    let path = dir.join(JOURNAL);
    let bytes = match std::fs::read(&path) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(error(format!("cannot read {}: {e}", path.display()))),
    };
    let complete = bytes.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
    if complete < bytes.len() {
        tracing::warn!(file = %path.display(), "dropping a last journal line torn by an interruption");
        esrp_results::truncate_to(&path, complete as u64)
            .map_err(|e| error(format!("cannot cut the torn line of {}: {e}", path.display())))?;
    }
    let mut attempts: Vec<Journaled> = Vec::new();
    let mut index: HashMap<(String, String), usize> = HashMap::new();
    // Attempts given back (never used): not attempts.
    let mut released = std::collections::HashSet::new();
    for (n, line) in bytes[..complete].split(|&b| b == b'\n').enumerate().filter(|(_, l)| !l.is_empty()) {
        let parsed: JournalLine = serde_json::from_slice(line)
            .map_err(|e| error(format!("{}:{}: not a journal line: {e}", path.display(), n + 1)))?;
        match parsed {
            JournalLine::Claim(claim) => {
                index.insert((claim.token.clone(), claim.scene.clone()), attempts.len());
                attempts.push(Journaled { claim, actions: Vec::new() });
            }
            JournalLine::Step { token, scene, action } => {
                if let Some(&i) = index.get(&(token, scene)) {
                    attempts[i].actions.push(action);
                }
            }
            JournalLine::Release { token, scene } => {
                if let Some(i) = index.remove(&(token, scene)) {
                    released.insert(i);
                }
            }
        }
    }
    Ok(attempts.into_iter().enumerate().filter(|(i, _)| !released.contains(i)).map(|(_, a)| a).collect())
}

/// The file, in the records folder, that lists the challenge's scenes (`esrp report
/// --leaderboard` scores every participant over all of them).
pub const CHALLENGE_SCENES: &str = "challenge-scenes.json";

/// A file the server creates and removes at start in the records folder, to learn whether it can
/// write there.
const WRITE_CHECK: &str = ".esrp-write-check";

/// Refuses a records folder that holds another challenge's records: its `challenge-scenes.json`
/// names another served dataset than `dataset_hash` (another challenge seed, number of hidden
/// scenes, benchmark or dataset). Checked before anything in the folder is read or written: the
/// old challenge's counted attempts would refuse the new challenge's scenes of the same ids as
/// played, its journal would be replayed on the new scenes, and its scene list, overwritten,
/// would no longer verify its records.
pub fn check_same_challenge(dir: &Path, dataset_hash: &str) -> Result<(), RecordsError> {
    let error = |reason: String| RecordsError { dir: dir.display().to_string(), reason };
    let path = dir.join(CHALLENGE_SCENES);
    if !path.is_file() {
        return Ok(()); // a new folder (or none yet, or not a folder: opening it says so)
    }
    let text = std::fs::read_to_string(&path).map_err(|e| error(format!("cannot read {}: {e}", path.display())))?;
    let recorded = serde_json::from_str::<serde_json::Value>(&text)
        .ok()
        .and_then(|manifest| manifest.get("dataset_hash").and_then(|h| h.as_str()).map(str::to_owned))
        .ok_or_else(|| error(format!("{} is not a scene list the server wrote (no dataset_hash)", path.display())))?;
    if recorded != dataset_hash {
        return Err(error(format!(
            "it holds the records of another challenge ({CHALLENGE_SCENES}: dataset_hash {recorded}; this server \
             serves {dataset_hash}: another --challenge-seed, --challenge-scenes, --minival-scenes, --benchmark, \
             --bench-seed or --dataset): give each challenge a folder of its own, or start with the flags this one \
             was recorded with"
        )));
    }
    Ok(())
}

/// Writes `DIR/challenge-scenes.json` (atomically: a temporary file renamed): the schema, the
/// served dataset's hash, what the hidden splits serve (`observations`: split → `paper` or
/// `full`) and each challenge scene's id, difficulty and object count.
pub fn write_challenge_scenes(
    dir: &Path,
    dataset_hash: &str,
    observations: serde_json::Value,
    scenes: &[crate::types::SceneInfo],
) -> Result<(), RecordsError> {
    let error = |reason: String| RecordsError { dir: dir.display().to_string(), reason };
    let listed: Vec<serde_json::Value> = scenes
        .iter()
        .filter(|s| s.split == esrp_core::Split::Challenge)
        .map(|s| {
            serde_json::json!({
                "id": s.id,
                "difficulty": s.difficulty.as_str(),
                "objects": s.movable_objects,
            })
        })
        .collect();
    let manifest = serde_json::json!({
        "schema": "esrp.challenge-scenes/v1",
        "dataset_hash": dataset_hash,
        "observations": observations,
        "scenes": listed,
    });
    let text = serde_json::to_string_pretty(&manifest).map_err(|e| error(e.to_string()))? + "\n";
    let path = dir.join(CHALLENGE_SCENES);
    write_atomically(&path, text.as_bytes(), 0o644).map_err(|e| error(format!("cannot write {}: {e}", path.display())))
}

/// Writes `bytes` to `path` whole or not at all: into `PATH.tmp` (permissions `mode`), synced,
/// then renamed over `path`.
fn write_atomically(path: &Path, bytes: &[u8], mode: u32) -> std::io::Result<()> {
    use std::os::unix::fs::OpenOptionsExt;
    let mut temporary = path.as_os_str().to_owned();
    temporary.push(".tmp");
    let mut file = std::fs::OpenOptions::new().write(true).create(true).truncate(true).mode(mode).open(&temporary)?;
    file.write_all(bytes)?;
    file.sync_all()?;
    std::fs::rename(&temporary, path)
}

/// A record on its way to its file; `done` hears when it is on disk.
struct Job {
    /// The file's name in the records folder: `<token>.jsonl`, or the attempts journal.
    file: String,
    line: Vec<u8>,
    /// Told once the line is on disk, or why it is not.
    done: tokio::sync::oneshot::Sender<Result<(), String>>,
}

/// Writes records: a thread appending lines to `DIR/<token>.jsonl`, one `fsync` per file per
/// batch of records that arrived together.
pub struct Recorder {
    dir: PathBuf,
    mode: RecordMode,
    key: RecordsKey,
    jobs: Mutex<Option<std::sync::mpsc::Sender<Job>>>,
    thread: Mutex<Option<std::thread::JoinHandle<()>>>,
}

/// A record's write, awaited before the answer that ended its episode leaves.
pub struct Written(Option<tokio::sync::oneshot::Receiver<Result<(), String>>>);

impl Written {
    /// Nothing to wait for.
    pub fn nothing() -> Self {
        Written(None)
    }

    /// Waits until the record is on disk (or its write failed, which the recorder logged).
    pub async fn wait(self) {
        let _ = self.outcome().await;
    }

    /// Waits until the record is on disk; says why it is not where its write failed (the folder
    /// gone, a full disk) or the recorder stopped before writing it.
    pub async fn outcome(self) -> Result<(), String> {
        match self.0 {
            None => Ok(()),
            Some(receiver) => receiver.await.unwrap_or_else(|_| Err("the records writer has stopped".to_owned())),
        }
    }
}

/// Why the records folder cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("--records {dir}: {reason}")]
pub struct RecordsError {
    /// The folder.
    pub dir: String,
    /// What went wrong.
    pub reason: String,
}

impl Recorder {
    /// Opens (creating it if needed) the records folder `dir`: reads every `*.jsonl` back,
    /// cutting a torn last line, and fills `attempts` with the counted attempts found; then
    /// starts the writer thread.
    pub fn open(dir: &Path, mode: RecordMode, attempts: &Attempts, key: Option<&Path>) -> Result<Self, RecordsError> {
        let error = |reason: String| RecordsError { dir: dir.display().to_string(), reason };
        if dir.exists() && !dir.is_dir() {
            return Err(error("not a folder: give a folder (it is created if missing)".into()));
        }
        std::fs::create_dir_all(dir).map_err(|e| error(format!("cannot create it: {e}")))?;
        let key = RecordsKey::load_or_create(dir, key)?;
        // Every record is written here as its episode ends: a folder the server cannot write in
        // is refused now, not found out as records are lost (a key already there, or given by
        // --records-key, is only read).
        let probe = dir.join(WRITE_CHECK);
        std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .open(&probe)
            .and_then(|_| std::fs::remove_file(&probe))
            .map_err(|e| error(format!("cannot write in it: {e}")))?;
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| error(format!("cannot list it: {e}")))?
            .filter_map(|entry| entry.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "jsonl"))
            .collect();
        files.sort();
        let mut counted = 0usize;
        for path in &files {
            let read = esrp_results::read_records(path).map_err(|e| error(e.to_string()))?;
            if read.torn_tail {
                tracing::warn!(file = %path.display(), "dropping a last record torn by an interruption");
                esrp_results::truncate_to(path, read.complete_bytes)
                    .map_err(|e| error(format!("cannot cut the torn line of {}: {e}", path.display())))?;
            }
            let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            for r in read.records.iter().filter(|r| r.counted == Some(true)) {
                attempts.ended(r.token.as_deref().unwrap_or(&stem), &r.scene_id, &r.finished_at);
                counted += 1;
            }
        }
        tracing::info!(dir = %dir.display(), files = files.len(), counted, mode = mode.as_str(), "records ready");
        let (sender, receiver) = std::sync::mpsc::channel::<Job>();
        let folder = dir.to_path_buf();
        let thread = std::thread::Builder::new()
            .name("esrp-records".into())
            .spawn(move || write_records(&folder, &receiver))
            .map_err(|e| error(format!("cannot start the writer thread: {e}")))?;
        Ok(Self { dir: dir.to_path_buf(), mode, key, jobs: Mutex::new(Some(sender)), thread: Mutex::new(Some(thread)) })
    }

    /// Which episodes are recorded.
    pub fn mode(&self) -> RecordMode {
        self.mode
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Signs `record` and queues it for `DIR/<token>.jsonl`; the returned [`Written`] completes
    /// once it is on disk.
    pub fn write(&self, record: &EpisodeRecord) -> Written {
        let token = record.token.clone().unwrap_or_else(|| "anonymous".into());
        let mut line = match self.signed_line(record) {
            Ok(line) => line,
            Err(e) => {
                tracing::error!(scene = %record.scene_id, "cannot encode a record: {e}");
                return Written::nothing();
            }
        };
        line.push(b'\n');
        self.queue(format!("{token}.jsonl"), line).unwrap_or_else(|| {
            tracing::error!(scene = %record.scene_id, "a record arrived after the recorder stopped: it is lost");
            Written::nothing()
        })
    }

    /// `record`'s line (without its newline) as the server writes it: its compact JSON with any
    /// signature it carried replaced by this server's.
    fn signed_line(&self, record: &EpisodeRecord) -> serde_json::Result<Vec<u8>> {
        let json = match record.signature {
            None => serde_json::to_vec(record)?,
            Some(_) => serde_json::to_vec(&EpisodeRecord { signature: None, ..record.clone() })?,
        };
        Ok(self.key.sign(&json))
    }

    /// Queues `line` for the file `file` of the folder; `None` once the recorder has stopped.
    fn queue(&self, file: String, line: Vec<u8>) -> Option<Written> {
        let (done, receiver) = tokio::sync::oneshot::channel();
        let jobs = self.jobs.lock().unwrap_or_else(|p| p.into_inner());
        jobs.as_ref()?.send(Job { file, line, done }).ok()?;
        Some(Written(Some(receiver)))
    }

    /// Journals the claim of `token`'s counted attempt at `scene`; the returned [`Written`]
    /// completes once the claim is on disk (the create waits for it before the episode exists:
    /// a crash after that cannot give the attempt back), and says so if it could not be written.
    pub fn claim(&self, claim: &Claim) -> Written {
        match self.journal(&JournalLine::Claim(claim.clone())) {
            Some(written) => written,
            None => {
                // Stopped: a claim that is not journaled must not make an episode.
                let (done, receiver) = tokio::sync::oneshot::channel();
                let _ = done.send(Err("the server is stopping: it records no more".to_owned()));
                Written(Some(receiver))
            }
        }
    }

    /// Journals one action of `token`'s counted attempt at `scene`, without waiting: it is on
    /// disk with the writer's next sync, a few milliseconds later.
    pub fn journal_step(&self, token: &str, scene: &str, action: u8) {
        self.journal(&JournalLine::Step { token: token.to_owned(), scene: scene.to_owned(), action });
    }

    /// Journals that `token`'s attempt at `scene` was given back, without waiting (a crash
    /// before it is on disk leaves the attempt counted, the safe side).
    pub fn journal_release(&self, token: &str, scene: &str) {
        self.journal(&JournalLine::Release { token: token.to_owned(), scene: scene.to_owned() });
    }

    /// Queues `line` for the attempts journal; `None` once the recorder has stopped (its
    /// [`Written`] may be dropped: the line is written all the same).
    fn journal(&self, line: &JournalLine) -> Option<Written> {
        let mut bytes = serde_json::to_vec(line).ok()?;
        bytes.push(b'\n');
        self.queue(JOURNAL.to_owned(), bytes)
    }

    /// Appends `record`, signed, to its token's file and syncs it, on the calling thread (the
    /// records of attempts a crash cut, written at start before anything is served).
    pub fn write_now(&self, record: &EpisodeRecord) -> Result<(), RecordsError> {
        let error = |reason: String| RecordsError { dir: self.dir.display().to_string(), reason };
        let token = record.token.clone().unwrap_or_else(|| "anonymous".into());
        let mut line = self.signed_line(record).map_err(|e| error(e.to_string()))?;
        line.push(b'\n');
        let path = self.dir.join(format!("{token}.jsonl"));
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| error(format!("cannot open {}: {e}", path.display())))?;
        file.write_all(&line)
            .and_then(|()| file.sync_data())
            .map_err(|e| error(format!("cannot write {}: {e}", path.display())))
    }

    /// Writes what is queued and stops the writer thread (at shutdown, after the last records).
    pub fn stop(&self) {
        self.jobs.lock().unwrap_or_else(|p| p.into_inner()).take();
        if let Some(thread) = self.thread.lock().unwrap_or_else(|p| p.into_inner()).take() {
            let _ = thread.join();
        }
    }
}

/// A record kept in a records folder: the token whose file holds it, its place among that
/// file's records (0-based), and the record.
#[derive(Debug)]
pub struct StoredRecord {
    /// The file's token (its name without `.jsonl`).
    pub token: String,
    /// Its place among the file's records.
    pub index: usize,
    /// The record.
    pub record: EpisodeRecord,
}

/// The records in folder `dir`: those of `token`'s file (every file's with `None`) and of scene
/// `scene` (any with `None`), file by file in name order, each file's in order. A last line
/// still being written (or torn) is left out; a file that cannot be read is an error.
pub fn stored_records(dir: &Path, token: Option<&str>, scene: Option<&str>) -> Result<Vec<StoredRecord>, RecordsError> {
    let error = |reason: String| RecordsError { dir: dir.display().to_string(), reason };
    let mut files: Vec<(String, PathBuf)> = std::fs::read_dir(dir)
        .map_err(|e| error(format!("cannot list it: {e}")))?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "jsonl"))
        .filter_map(|p| Some((p.file_stem()?.to_str()?.to_owned(), p)))
        // The file is chosen by comparing names, never by joining a client's text to a path.
        .filter(|(stem, _)| token.is_none_or(|t| t == stem))
        .collect();
    files.sort();
    let mut found = Vec::new();
    for (stem, path) in files {
        let read = esrp_results::read_records(&path).map_err(|e| error(e.to_string()))?;
        found.extend(
            read.records
                .into_iter()
                .enumerate()
                .filter(|(_, r)| scene.is_none_or(|s| r.scene_id == s))
                .map(|(index, record)| StoredRecord { token: stem.clone(), index, record }),
        );
    }
    Ok(found)
}

/// The writer thread: takes every job waiting, appends each line to its token's file, syncs
/// each file written once, then acknowledges the jobs.
fn write_records(dir: &Path, jobs: &std::sync::mpsc::Receiver<Job>) {
    let mut files: HashMap<String, File> = HashMap::new();
    while let Ok(first) = jobs.recv() {
        let mut batch = vec![first];
        batch.extend(jobs.try_iter());
        let mut touched: Vec<String> = Vec::new();
        // What went wrong with each job's line, by its place in the batch.
        let mut failed: Vec<Option<String>> = vec![None; batch.len()];
        for (job, failure) in batch.iter().zip(&mut failed) {
            let file = match files.entry(job.file.clone()) {
                std::collections::hash_map::Entry::Occupied(f) => f.into_mut(),
                std::collections::hash_map::Entry::Vacant(v) => {
                    let path = dir.join(&job.file);
                    match std::fs::OpenOptions::new().create(true).append(true).open(&path) {
                        Ok(f) => v.insert(f),
                        Err(e) => {
                            tracing::error!(file = %path.display(), "cannot open a records file: {e}; the record is lost");
                            *failure = Some(format!("cannot open {}: {e}", path.display()));
                            continue;
                        }
                    }
                }
            };
            // One write per line: a crash leaves whole lines and at most one torn last line. A
            // write that fails (a full disk) is cut off again, so that the lines after it are
            // not appended to a torn one.
            let length = file.metadata().map(|m| m.len());
            if let Err(e) = file.write_all(&job.line) {
                tracing::error!(file = %job.file, "cannot write a record: {e}; it is lost");
                if let Ok(length) = length {
                    let _ = file.set_len(length);
                }
                *failure = Some(format!("cannot write {}: {e}", job.file));
            }
            if !touched.contains(&job.file) {
                touched.push(job.file.clone());
            }
        }
        for name in &touched {
            if let Some(Err(e)) = files.get(name).map(File::sync_data) {
                tracing::error!(file = %name, "cannot sync a records file: {e}");
                for (job, failure) in batch.iter().zip(&mut failed) {
                    if job.file == *name && failure.is_none() {
                        *failure = Some(format!("cannot sync {name}: {e}"));
                    }
                }
            }
        }
        for (job, failure) in batch.into_iter().zip(failed) {
            let _ = job.done.send(failure.map_or(Ok(()), Err));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::Role;

    fn caller(name: &str) -> Caller {
        Caller { name: name.into(), role: Role::Agent, max_episodes: None, max_streams: None }
    }

    #[test]
    fn a_signed_line_verifies_and_any_change_breaks_it() {
        let key = RecordsKey::from_bytes(b"0123456789abcdef0123456789abcdef");
        let json = br#"{"scene_id":"challenge/00001","success":true,"steps":12}"#;
        let line = key.sign(json);
        let text = String::from_utf8(line.clone()).unwrap();
        assert!(text.starts_with(r#"{"scene_id":"challenge/00001","success":true,"steps":12,"signature":""#), "{text}");
        assert!(key.verify(&line));
        let altered = text.replace("true", "false");
        assert!(!key.verify(altered.as_bytes()), "a changed field");
        assert!(!key.verify(json), "an unsigned line");
        let other = RecordsKey::from_bytes(b"another key, just as long as that");
        assert!(!other.verify(&line), "another key");
        let mut cut = line.clone();
        cut.truncate(line.len() - 2);
        assert!(!key.verify(&cut), "a torn line");
    }

    #[test]
    fn the_journal_reads_back_claims_and_actions_and_cuts_a_torn_line() {
        let dir = tempfile::tempdir().unwrap();
        let claim = |token: &str, scene: &str| {
            serde_json::json!({"claim": {"token": token, "scene": scene, "agent": "a", "started_at": "2026-11-26T20:00:00Z", "config": {"horizon": 50}}})
                .to_string()
        };
        let step = |token: &str, scene: &str, action: u8| {
            serde_json::json!({"step": {"token": token, "scene": scene, "action": action}}).to_string()
        };
        let release = serde_json::json!({"release": {"token": "bob", "scene": "challenge/00002"}}).to_string();
        let lines = [
            claim("alice", "challenge/00001"),
            step("alice", "challenge/00001", 2),
            claim("bob", "challenge/00002"),
            release,
            step("alice", "challenge/00001", 0),
        ];
        let mut text = lines.join("\n") + "\n";
        text.push_str(r#"{"step": {"token": "alice", "sce"#);
        std::fs::write(dir.path().join(JOURNAL), &text).unwrap();
        let read = read_journal(dir.path()).unwrap();
        assert_eq!(read.len(), 1, "bob's claim was given back: {read:?}");
        assert_eq!((read[0].claim.token.as_str(), read[0].actions.as_slice()), ("alice", &[2u8, 0][..]));
        assert_eq!(read[0].claim.config.horizon, Some(50));
        let kept = std::fs::read_to_string(dir.path().join(JOURNAL)).unwrap();
        assert!(kept.ends_with("\n") && kept.len() < text.len(), "the torn line is cut");
        assert!(read_journal(tempfile::tempdir().unwrap().path()).unwrap().is_empty(), "no journal, no attempts");
        std::fs::write(dir.path().join(JOURNAL), "not json\n").unwrap();
        assert!(read_journal(dir.path()).unwrap_err().to_string().contains("not a journal line"));
    }

    #[test]
    fn a_claim_says_whether_it_was_journaled() {
        let dir = tempfile::tempdir().unwrap();
        let folder = dir.path().join("records");
        let recorder = Recorder::open(&folder, RecordMode::Challenge, &Attempts::default(), None).unwrap();
        let claim = Claim {
            token: "bob".into(),
            scene: "challenge/00001".into(),
            agent: "a".into(),
            started_at: "2026-11-29T11:00:00Z".into(),
            config: Default::default(),
        };
        let runtime = tokio::runtime::Builder::new_current_thread().build().unwrap();
        let outcome = |written: Written| runtime.block_on(written.outcome());
        // The folder gone (the journal not yet opened): the claim is not on disk, and says why.
        std::fs::rename(&folder, dir.path().join("away")).unwrap();
        let why = outcome(recorder.claim(&claim)).unwrap_err();
        assert!(why.contains("cannot open") && why.contains(JOURNAL), "{why}");
        std::fs::rename(dir.path().join("away"), &folder).unwrap();
        assert_eq!(outcome(recorder.claim(&claim)), Ok(()));
        assert_eq!(read_journal(&folder).unwrap().len(), 1, "the journaled claim is read back");
        // Stopped (shutting down), the recorder journals no claim.
        recorder.stop();
        let why = outcome(recorder.claim(&claim)).unwrap_err();
        assert!(why.contains("stopping"), "{why}");
    }

    #[test]
    fn the_key_is_generated_once_and_kept_private() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let first = RecordsKey::load_or_create(dir.path(), None).unwrap();
        let path = dir.path().join(GENERATED_KEY);
        assert_eq!(std::fs::metadata(&path).unwrap().permissions().mode() & 0o777, 0o600);
        assert_eq!(std::fs::read_to_string(&path).unwrap().len(), 64);
        let again = RecordsKey::load_or_create(dir.path(), None).unwrap();
        assert_eq!(first.0, again.0, "the key is read back, not made again");
        let short = dir.path().join("short.key");
        std::fs::write(&short, "tiny\n").unwrap();
        let refused = RecordsKey::load_or_create(dir.path(), Some(&short)).unwrap_err().to_string();
        assert!(refused.contains("at least 16"), "{refused}");
    }

    #[test]
    fn one_counted_attempt_per_scene_and_token() {
        let attempts = Attempts::default();
        let (alice, bob) = (caller("alice"), caller("bob"));
        attempts.take(&alice, "challenge/00001").unwrap();
        attempts.take(&bob, "challenge/00001").unwrap();
        let again = attempts.take(&alice, "challenge/00001").unwrap_err().to_string();
        assert!(again.contains("already played by token \"alice\"") && again.contains("still running"), "{again}");
        attempts.give_back(&alice.name, "challenge/00001");
        attempts.take(&alice, "challenge/00001").unwrap();
        attempts.ended("alice", "challenge/00001", "2026-11-25T20:00:00Z");
        let ended = attempts.take(&alice, "challenge/00001").unwrap_err().to_string();
        assert!(ended.contains("ended 2026-11-25T20:00:00Z"), "{ended}");
        assert_eq!(attempts.len(), 2);
    }
}
