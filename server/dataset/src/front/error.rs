//! What can be wrong with an import's input ([`FrontError`]).

use std::path::PathBuf;

/// Something wrong with the input; each variant names the file and says how to fix it.
#[derive(Debug, thiserror::Error)]
pub enum FrontError {
    /// A file or directory could not be read.
    #[error("cannot read {path}: {source}; check that it exists and is readable")]
    Io {
        /// The path.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A house file is not 3D-FRONT JSON.
    #[error(
        "{path} is not a 3D-FRONT house file: {message}; re-extract it from the 3D-FRONT archive or remove it from the directory"
    )]
    HouseJson {
        /// The house file.
        path: PathBuf,
        /// What is wrong, with line and column.
        message: String,
    },
    /// `model_info.json` is not 3D-FUTURE's model list.
    #[error(
        "{path} is not 3D-FUTURE's model_info.json (a list of {{model_id, super-category, category}}): {message}; re-extract it from the 3D-FUTURE archive"
    )]
    ModelInfo {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// No `model_info.json` was found.
    #[error(
        "no model_info.json in {dir} or {dir}/3D-FUTURE-model: pass the 3D-FUTURE directory (the one holding model_info.json and the <jid>/raw_model.obj folders) as --future"
    )]
    MissingModelInfo {
        /// The directory given.
        dir: PathBuf,
    },
    /// The 3D-FRONT directory holds no house file.
    #[error("no house files (*.json) in {dir}: pass the 3D-FRONT directory holding the <uuid>.json files as --front")]
    NoHouses {
        /// The directory given.
        dir: PathBuf,
    },
    /// An OBJ file could not be parsed.
    #[error("{path}, line {line}: {message}")]
    Obj {
        /// The OBJ file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        message: String,
    },
}
