//! **esrp-results**: the results schema `esrp.results/v1` that every evaluation tool writes
//! (Rust `esrp-eval`, Python `esrp eval`) and the server's own records (`esrp-server
//! --records`), as `docs/evaluation.md` describes it: one [`EpisodeRecord`] per line of a JSON
//! Lines file; [`read_records`] reads a file back (dropping a last line that an interruption
//! cut short), [`append_record`] writes one. Plain data and file I/O: the client's summaries
//! (`esrp_client::results`) and the server's recorder build on it.

#![warn(missing_docs)]

use std::io::{BufRead, BufReader, Write};
use std::path::Path;

use serde::{Deserialize, Serialize};

/// The schema tag of every record.
pub const SCHEMA: &str = "esrp.results/v1";

/// One finished episode (a line of a results file).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    /// Always [`SCHEMA`].
    pub schema: String,
    /// The scene's id.
    pub scene_id: String,
    /// The served dataset's name.
    pub dataset: String,
    /// `train`, `test`, `challenge` or `minival`.
    pub split: String,
    /// The room type.
    pub room_type: String,
    /// `easy`, `medium` or `hard`.
    pub difficulty: String,
    /// Number of movable objects.
    pub objects: u32,
    /// The agent's name.
    pub agent: String,
    /// The agent's settings.
    pub agent_config: serde_json::Map<String, serde_json::Value>,
    /// The per-scene seed the agent used, if it draws random numbers.
    pub seed: Option<u64>,
    /// Every object placed.
    pub success: bool,
    /// Objects placed over objects.
    pub osr: f64,
    /// Remaining over initial distance.
    pub rdr: f64,
    /// SPEC §5 stage, 1..=4.
    pub stage: u32,
    /// Objects placed at the end.
    pub placed: u32,
    /// Steps taken.
    pub steps: u32,
    /// The episode's step limit.
    pub horizon: u32,
    /// `success`, `horizon` or `agent`.
    pub end: String,
    /// The sum of the rewards.
    pub total_reward: f64,
    /// Every action taken, as codes 0..=5.
    pub actions: Vec<u8>,
    /// Wall time from creation to the end.
    pub wall_seconds: f64,
    /// Agent-specific statistics.
    pub agent_stats: serde_json::Map<String, serde_json::Value>,
    /// The server's version.
    pub server_version: String,
    /// The tool that wrote the record.
    pub client: String,
    /// RFC 3339 UTC time of the episode's end.
    pub finished_at: String,
    /// `Some(true)` for a privileged episode (one that could read the simulator's state): the
    /// server's records of privileged episodes say it, and Python's `esrp eval --privileged` for
    /// an agent whose name does not (`plan` and `expert` always play privileged). Absent
    /// otherwise, never `false`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub privileged: Option<bool>,
    /// Server records only: the name of the token that played the episode.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub token: Option<String>,
    /// Server records only: RFC 3339 UTC time of the episode's creation (or reset).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub started_at: Option<String>,
    /// Server records only: a hash of the served dataset's seeds (16 hex digits), the same for
    /// every server serving the same scenes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dataset_hash: Option<String>,
    /// Server records only: whether this is the token's one counted attempt on a challenge
    /// scene (the first).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub counted: Option<bool>,
    /// Server records only: the reward weights the episode played with (`success`, `place`,
    /// `unplace`, `potential`, `holding`, `living`), so that a replay pays the same rewards.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reward_weights: Option<serde_json::Map<String, serde_json::Value>>,
    /// Server records only: what the episode served its client: `paper` (the paper's
    /// observation only, a hidden scene's) or `full`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observations: Option<String>,
    /// Server records only: HMAC-SHA256 (hex) of the record's line without this member, with
    /// the server's records key; always the line's last member (docs/evaluation.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub signature: Option<String>,
}

/// Why a results file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ResultsError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The cause.
        source: std::io::Error,
    },
    /// A line (not the last) is not a record.
    #[error("{path}:{line}: not an {SCHEMA} record: {reason}")]
    BadLine {
        /// The file.
        path: String,
        /// The 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
}

/// A results file read back.
#[derive(Debug, Default)]
pub struct ReadRecords {
    /// The records, in file order.
    pub records: Vec<EpisodeRecord>,
    /// Byte length of the complete lines read: a last line cut short by an interruption ends
    /// after this, and [`truncate_to`] removes it.
    pub complete_bytes: u64,
    /// Whether the last line was cut short: it lacks its newline (an interrupted write).
    pub torn_tail: bool,
}

/// Reads a results file. A last line without its newline (a write interrupted before it: the
/// newline is the last byte an append writes) is reported in [`ReadRecords::torn_tail`], not an
/// error, when it is a record or begins as a record line does ([`may_be_cut_record`]); any
/// other line that is not a record is, the last one too (a file given by mistake is refused,
/// never cut). Blank lines are skipped.
pub fn read_records(path: &Path) -> Result<ReadRecords, ResultsError> {
    let name = path.display().to_string();
    let io = |source| ResultsError::Io { path: name.clone(), source };
    let file = std::fs::File::open(path).map_err(io)?;
    let mut reader = BufReader::new(file);
    let mut out = ReadRecords::default();
    let mut line = Vec::new();
    let mut number = 0;
    loop {
        line.clear();
        let n = reader.read_until(b'\n', &mut line).map_err(io)?;
        if n == 0 {
            break;
        }
        number += 1;
        let complete = line.ends_with(b"\n");
        // A line that is not UTF-8 (a gzip-compressed file, say) is a bad line like any other.
        let text = std::str::from_utf8(&line).map(str::trim).map_err(|e| format!("not UTF-8 text ({e})"));
        if text.as_ref().is_ok_and(|t| t.is_empty()) {
            if complete {
                out.complete_bytes += n as u64;
            }
            continue;
        }
        match (text.and_then(parse_record), complete) {
            (Ok(record), true) => {
                out.records.push(record);
                out.complete_bytes += n as u64;
            }
            // A line without its newline is the file's last (read_until read to the end): a write
            // interrupted before its newline, the last byte an append writes, if it is a record
            // or begins as a record line does.
            (Ok(_), false) => out.torn_tail = true,
            (Err(_), false) if may_be_cut_record(&line) => out.torn_tail = true,
            // A whole line that is not a record is no interrupted write, even the last, and
            // neither is a last line that begins otherwise (a one-line JSON file as most JSON
            // writers leave it, without its newline): refused, never cut off (it may be a file
            // given by mistake).
            (Err(reason), _) => return Err(ResultsError::BadLine { path: name, line: number, reason }),
        }
    }
    Ok(out)
}

/// How every tool's record line begins (the Rust tools', Python's and the server's).
pub const RECORD_START: &[u8] = br#"{"schema":"esrp.results/v1""#;

/// Whether `line`, a last line without its newline, may be a record whose append was cut short:
/// it begins as a record line does ([`RECORD_START`], ASCII spaces aside), or is a beginning of it.
pub fn may_be_cut_record(line: &[u8]) -> bool {
    let squeezed: Vec<u8> = line.iter().copied().filter(|b| !b" \t\r\n".contains(b)).collect();
    squeezed.starts_with(RECORD_START) || RECORD_START.starts_with(&squeezed)
}

fn parse_record(text: &str) -> Result<EpisodeRecord, String> {
    let record: EpisodeRecord = serde_json::from_str(text).map_err(|e| e.to_string())?;
    if record.schema != SCHEMA {
        return Err(format!("schema is {:?}, not {SCHEMA:?}", record.schema));
    }
    if let Some(code) = record.actions.iter().find(|&&a| a > 5) {
        return Err(format!("field `actions` holds {code}, not an action code 0..5"));
    }
    Ok(record)
}

/// Cuts a results file to its first `bytes` bytes (dropping a torn last line).
pub fn truncate_to(path: &Path, bytes: u64) -> std::io::Result<()> {
    std::fs::OpenOptions::new().write(true).open(path)?.set_len(bytes)
}

/// Appends one record as a line and flushes it.
pub fn append_record(out: &mut impl Write, record: &EpisodeRecord) -> std::io::Result<()> {
    let mut line = serde_json::to_vec(record).map_err(std::io::Error::other)?;
    line.push(b'\n');
    out.write_all(&line)?;
    out.flush()
}

/// Records for tests: the one fixture the results crate's tests and the client's summaries'
/// tests build their records from (compiled always, as it is small, so that no feature splits
/// the workspace's builds).
#[doc(hidden)]
pub mod testing {
    use super::{EpisodeRecord, SCHEMA};

    /// A record of scene `scene` with the given outcome and plausible values elsewhere: 10 steps of
    /// a 200-step horizon by the `random` agent, ended by success or by the horizon.
    pub fn record(scene: &str, difficulty: &str, success: bool, osr: f64, rdr: f64, stage: u32) -> EpisodeRecord {
        EpisodeRecord {
            schema: SCHEMA.into(),
            scene_id: scene.into(),
            dataset: "d".into(),
            split: "test".into(),
            room_type: "Bedroom".into(),
            difficulty: difficulty.into(),
            objects: 1,
            agent: "random".into(),
            agent_config: Default::default(),
            seed: Some(3),
            success,
            osr,
            rdr,
            stage,
            placed: u32::from(success),
            steps: 10,
            horizon: 200,
            end: if success { "success" } else { "horizon" }.into(),
            total_reward: 1.5,
            actions: vec![0; 10],
            wall_seconds: 0.1,
            agent_stats: Default::default(),
            server_version: "0.1.0".into(),
            client: "test".into(),
            finished_at: "2026-11-23T00:00:00Z".into(),
            privileged: None,
            token: None,
            started_at: None,
            dataset_hash: None,
            counted: None,
            reward_weights: None,
            observations: None,
            signature: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::testing::record;
    use super::*;

    #[test]
    fn a_torn_last_line_is_dropped_and_other_bad_lines_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.jsonl");
        let mut bytes = Vec::new();
        append_record(&mut bytes, &record("a", "easy", true, 1.0, 0.0, 4)).unwrap();
        append_record(&mut bytes, &record("b", "easy", true, 1.0, 0.0, 4)).unwrap();
        let whole = bytes.len() as u64;
        bytes.extend_from_slice(br#"{"schema":"esrp.results/v1","scene_id":"c""#);
        std::fs::write(&path, &bytes).unwrap();
        let read = read_records(&path).unwrap();
        assert_eq!(read.records.len(), 2);
        assert!(read.torn_tail);
        assert_eq!(read.complete_bytes, whole);
        truncate_to(&path, read.complete_bytes).unwrap();
        let again = read_records(&path).unwrap();
        assert_eq!((again.records.len(), again.torn_tail), (2, false));
        assert_eq!(again.records[1], record("b", "easy", true, 1.0, 0.0, 4));

        // A bad line followed by a good one is not a torn tail.
        let mut bad = b"not json\n".to_vec();
        append_record(&mut bad, &record("a", "easy", true, 1.0, 0.0, 4)).unwrap();
        std::fs::write(&path, &bad).unwrap();
        let err = read_records(&path).unwrap_err();
        assert!(matches!(err, ResultsError::BadLine { line: 1, .. }), "{err}");

        // A whole last line that is not a record is no interrupted write: an error, not cut off.
        let mut whole_bad = Vec::new();
        append_record(&mut whole_bad, &record("a", "easy", true, 1.0, 0.0, 4)).unwrap();
        whole_bad.extend_from_slice(b"{\"learning_rate\": 0.001}\n");
        std::fs::write(&path, &whole_bad).unwrap();
        let err = read_records(&path).unwrap_err();
        assert!(matches!(err, ResultsError::BadLine { line: 2, .. }), "{err}");
        std::fs::write(&path, b"{\"epochs\": 100}\n").unwrap();
        assert!(matches!(read_records(&path).unwrap_err(), ResultsError::BadLine { line: 1, .. }));
    }

    #[test]
    fn lines_of_something_else_are_refused_never_cut_off() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.jsonl");
        // A one-line JSON file as most writers leave it (no newline) is no record cut short: it
        // was cut off (the file lost) by a resuming esrp-eval.
        std::fs::write(&path, br#"{"learning_rate": 0.001, "epochs": 100}"#).unwrap();
        let err = read_records(&path).unwrap_err();
        assert!(matches!(err, ResultsError::BadLine { line: 1, .. }), "{err}");
        // A gzip-compressed file (not UTF-8) names its line instead of "cannot read".
        let mut gzip = b"\x1f\x8b\x08\x00\xff\xfe\n".to_vec();
        append_record(&mut gzip, &record("a", "easy", true, 1.0, 0.0, 4)).unwrap();
        std::fs::write(&path, &gzip).unwrap();
        let err = read_records(&path).unwrap_err();
        assert!(
            matches!(&err, ResultsError::BadLine { line: 1, reason, .. } if reason.starts_with("not UTF-8")),
            "{err}"
        );
        // Action codes are 0..5, as the Python reader reads them.
        let mut bad = serde_json::to_string(&record("a", "easy", true, 1.0, 0.0, 4)).unwrap();
        bad = bad.replace(r#""actions":[0,0"#, r#""actions":[6,0"#) + "\n";
        std::fs::write(&path, bad).unwrap();
        let err = read_records(&path).unwrap_err();
        assert!(
            err.to_string()
                .ends_with(":1: not an esrp.results/v1 record: field `actions` holds 6, not an action code 0..5"),
            "{err}"
        );
        // What an interrupted append leaves is still dropped: any beginning of a record line,
        // as short as one byte, spaced as Python's json.dumps spaces it, or a whole record.
        let mut line = Vec::new();
        append_record(&mut line, &record("a", "easy", true, 1.0, 0.0, 4)).unwrap();
        for cut in
            [&line[..1], &line[..10], &line[..40], &line[..line.len() - 1], br#"{"schema": "esrp.results/v1", "sc"#]
        {
            let mut bytes = line.clone();
            bytes.extend_from_slice(cut);
            std::fs::write(&path, &bytes).unwrap();
            let read = read_records(&path).unwrap();
            assert_eq!((read.records.len(), read.torn_tail, read.complete_bytes), (1, true, line.len() as u64));
        }
    }

    #[test]
    fn the_privileged_mark_is_kept_and_never_written_false() {
        let plain = record("a", "easy", true, 1.0, 0.0, 4);
        assert!(!serde_json::to_string(&plain).unwrap().contains("privileged"));
        let marked = EpisodeRecord { privileged: Some(true), ..plain };
        let line = serde_json::to_string(&marked).unwrap();
        assert!(line.contains(r#""finished_at":"2026-11-23T00:00:00Z","privileged":true}"#), "{line}");
        assert_eq!(serde_json::from_str::<EpisodeRecord>(&line).unwrap(), marked);
    }

    #[test]
    fn server_fields_round_trip_and_are_left_out_when_absent() {
        let plain = record("a", "easy", true, 1.0, 0.0, 4);
        let line = serde_json::to_string(&plain).unwrap();
        assert!(!line.contains("token") && !line.contains("counted"), "{line}");
        let server = EpisodeRecord { token: Some("alice".into()), counted: Some(true), ..plain };
        let back: EpisodeRecord = serde_json::from_str(&serde_json::to_string(&server).unwrap()).unwrap();
        assert_eq!(back, server);
    }
}
