//! A built-in benchmark's generated scenes in one file, each compressed on its own: what the
//! server ships so that the built-in benchmark is as fast as a generated folder from the first
//! minute (generating a scene takes tens of milliseconds; reading it from the pack, tens of
//! microseconds).
//!
//! Layout: the line `esrp-scene-pack/v1`, a JSON header line ([`PackHeader`]: the benchmark, its
//! seed, the [`GENERATOR_VERSION`] that made it and the scene count), then for each scene its
//! compressed length (u32, little-endian) and its JSON (the same text a scene cache file holds,
//! `serde_json::to_string`), compressed with DEFLATE. A pack is found again only by the generator
//! that made it: [`ScenePack::serves`] checks the benchmark, seed, version and count.

use std::io::{Read, Write};

use esrp_core::Scene;
use flate2::Compression;
use flate2::read::DeflateDecoder;
use flate2::write::DeflateEncoder;
use serde::{Deserialize, Serialize};

use crate::benchmark::Benchmark;
use crate::cache::GENERATOR_VERSION;

/// The pack's first line.
const MAGIC: &str = "esrp-scene-pack/v1";

/// What a pack holds.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PackHeader {
    /// The benchmark's name (`esrp-bench-v2`).
    pub benchmark: String,
    /// Its seed.
    pub seed: u64,
    /// The generator that made the scenes ([`GENERATOR_VERSION`]).
    pub generator: String,
    /// How many scenes, in index order.
    pub count: usize,
}

/// Why a pack cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum PackError {
    /// Not a scene pack, or cut short.
    #[error("not a scene pack: {0}")]
    Format(String),
    /// A scene's bytes do not inflate to a scene.
    #[error("scene {index} of the pack: {reason}")]
    Scene {
        /// Its index.
        index: usize,
        /// What is wrong.
        reason: String,
    },
}

/// The JSON a scene has in packs and scene caches.
pub fn scene_json(scene: &Scene) -> String {
    serde_json::to_string(scene).unwrap_or_default()
}

/// Writes the pack of `scenes` (each scene's JSON, in index order) of `bench`.
pub fn write_pack(bench: &Benchmark, scenes: &[String], out: &mut impl Write) -> std::io::Result<()> {
    let header = PackHeader {
        benchmark: bench.name(),
        seed: bench.seed(),
        generator: GENERATOR_VERSION.to_owned(),
        count: scenes.len(),
    };
    writeln!(out, "{MAGIC}")?;
    writeln!(out, "{}", serde_json::to_string(&header).unwrap_or_default())?;
    for json in scenes {
        let mut encoder = DeflateEncoder::new(Vec::new(), Compression::best());
        encoder.write_all(json.as_bytes())?;
        let compressed = encoder.finish()?;
        let length = u32::try_from(compressed.len()).map_err(std::io::Error::other)?;
        out.write_all(&length.to_le_bytes())?;
        out.write_all(&compressed)?;
    }
    Ok(())
}

/// A pack read from its bytes (borrowed: a pack built into a binary is never copied).
#[derive(Clone, Debug)]
pub struct ScenePack<'a> {
    header: PackHeader,
    /// Each scene's compressed bytes.
    entries: Vec<&'a [u8]>,
}

impl<'a> ScenePack<'a> {
    /// Reads the header and the index of `bytes`.
    pub fn parse(bytes: &'a [u8]) -> Result<Self, PackError> {
        let format = |why: &str| PackError::Format(why.to_owned());
        let mut lines = bytes.splitn(3, |&b| b == b'\n');
        if lines.next() != Some(MAGIC.as_bytes()) {
            return Err(format("it does not begin with esrp-scene-pack/v1"));
        }
        let header: PackHeader = serde_json::from_slice(lines.next().ok_or_else(|| format("no header"))?)
            .map_err(|e| PackError::Format(format!("its header: {e}")))?;
        let mut rest = lines.next().unwrap_or_default();
        let mut entries = Vec::with_capacity(header.count.min(1 << 20));
        while !rest.is_empty() {
            let (length, after) = rest.split_at_checked(4).ok_or_else(|| format("cut short in a length"))?;
            let length = u32::from_le_bytes([length[0], length[1], length[2], length[3]]) as usize;
            let (entry, after) = after.split_at_checked(length).ok_or_else(|| format("cut short in a scene"))?;
            entries.push(entry);
            rest = after;
        }
        if entries.len() != header.count {
            return Err(PackError::Format(format!(
                "it holds {} scenes, its header says {}",
                entries.len(),
                header.count
            )));
        }
        Ok(Self { header, entries })
    }

    /// What it holds.
    pub fn header(&self) -> &PackHeader {
        &self.header
    }

    /// Whether it holds every scene of `bench` as this generator makes them.
    pub fn serves(&self, bench: &Benchmark) -> bool {
        self.header.benchmark == bench.name()
            && self.header.seed == bench.seed()
            && self.header.generator == GENERATOR_VERSION
            && self.header.count == bench.len()
    }

    /// Scene `index`'s JSON.
    pub fn json(&self, index: usize) -> Result<String, PackError> {
        let entry = self
            .entries
            .get(index)
            .ok_or_else(|| PackError::Scene { index, reason: format!("the pack has {} scenes", self.entries.len()) })?;
        let mut json = String::new();
        DeflateDecoder::new(*entry)
            .read_to_string(&mut json)
            .map_err(|e| PackError::Scene { index, reason: e.to_string() })?;
        Ok(json)
    }

    /// Scene `index`.
    pub fn scene(&self, index: usize) -> Result<Scene, PackError> {
        Scene::from_json(&self.json(index)?).map_err(|e| PackError::Scene { index, reason: e.to_string() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::BenchVersion;

    #[test]
    fn a_pack_gives_back_the_scenes_it_was_written_with() {
        let bench = Benchmark::new(BenchVersion::default(), 0);
        let scenes: Vec<String> = (0..3).map(|i| scene_json(&bench.generate(i).unwrap().scene)).collect();
        let mut bytes = Vec::new();
        write_pack(&bench, &scenes, &mut bytes).unwrap();
        let pack = ScenePack::parse(&bytes).unwrap();
        assert_eq!(pack.header().count, 3);
        assert!(!pack.serves(&bench), "three scenes are not the whole benchmark");
        for (i, json) in scenes.iter().enumerate() {
            assert_eq!(&pack.json(i).unwrap(), json);
            assert_eq!(scene_json(&pack.scene(i).unwrap()), *json);
        }
        assert!(matches!(pack.json(3), Err(PackError::Scene { index: 3, .. })));
        // Cut short, or not a pack at all: a typed error, never a panic.
        for cut in [bytes.len() - 1, 30, 5, 0] {
            assert!(ScenePack::parse(&bytes[..cut]).is_err(), "{cut}");
        }
        assert!(ScenePack::parse(b"esrp-scene-pack/v1\n{}\n").is_err());
    }
}
