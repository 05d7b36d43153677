//! The model library: each 3D-FUTURE model's geometry (its hull or bounding box), loaded once.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use esrp_core::parry3d;
use parry3d::math::Vector;

use super::error::FrontError;
use super::json::ModelInfo;
use super::obj::parse_obj;
use super::outline::bounds;

/// A model's geometry, cached by jid: the vertices of its convex hull in the model's frame
/// (a hull commutes with scaling and rotation), or why there is none.
#[derive(Clone, Debug)]
pub(super) enum ModelGeometry {
    Hull(Vec<[f64; 3]>),
    Missing,
}

/// The convex hull vertices of `points`, or their bounding box corners when the hull is
/// degenerate (flat models).
pub(super) fn hull_vertices(points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let vectors: Vec<Vector> = points.iter().map(|p| Vector::new(p[0], p[1], p[2])).collect();
    match parry3d::transformation::try_convex_hull(&vectors) {
        Ok((vertices, _)) if vertices.len() >= 4 => vertices.iter().map(|v| [v.x, v.y, v.z]).collect(),
        _ => box_corners(points),
    }
}

pub(super) fn box_corners(points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let Some((lo, hi)) = bounds(points.iter().copied()) else { return Vec::new() };
    let mut corners = Vec::with_capacity(8);
    for k in 0..8 {
        corners.push([
            if k & 1 == 0 { lo[0] } else { hi[0] },
            if k & 2 == 0 { lo[1] } else { hi[1] },
            if k & 4 == 0 { lo[2] } else { hi[2] },
        ]);
    }
    corners
}

pub(super) struct Library {
    pub(super) model_root: PathBuf,
    pub(super) info: HashMap<String, (String, String)>,
    pub(super) models: HashMap<String, ModelGeometry>,
}

impl Library {
    pub(super) fn open(future_dir: &Path) -> Result<Self, FrontError> {
        let nested = future_dir.join("3D-FUTURE-model");
        let model_root = if nested.is_dir() { nested } else { future_dir.to_owned() };
        let info_path = [future_dir.join("model_info.json"), model_root.join("model_info.json")]
            .into_iter()
            .find(|p| p.is_file())
            .ok_or_else(|| FrontError::MissingModelInfo { dir: future_dir.to_owned() })?;
        let text =
            std::fs::read_to_string(&info_path).map_err(|source| FrontError::Io { path: info_path.clone(), source })?;
        let entries: Vec<ModelInfo> = serde_json::from_str(&text)
            .map_err(|e| FrontError::ModelInfo { path: info_path.clone(), message: e.to_string() })?;
        let info = entries
            .into_iter()
            .map(|m| (m.model_id, (m.category.unwrap_or_default(), m.super_category.unwrap_or_default())))
            .collect();
        Ok(Self { model_root, info, models: HashMap::new() })
    }

    /// The model's hull, reading and caching its OBJ; warns once per model that is missing or
    /// unreadable.
    pub(super) fn geometry(&mut self, jid: &str, warnings: &mut Vec<String>) -> ModelGeometry {
        if let Some(g) = self.models.get(jid) {
            return g.clone();
        }
        let path = self.model_root.join(jid).join("raw_model.obj");
        let geometry = match std::fs::read_to_string(&path) {
            Ok(text) => match parse_obj(&text, &path) {
                Ok(mesh) => ModelGeometry::Hull(hull_vertices(&mesh.vertices)),
                Err(e) => {
                    warnings.push(format!("model {jid}: {e}; using its bounding box"));
                    ModelGeometry::Missing
                }
            },
            Err(_) => {
                warnings.push(format!("model {jid}: {} is missing; using its bounding box", path.display()));
                ModelGeometry::Missing
            }
        };
        self.models.insert(jid.to_owned(), geometry.clone());
        geometry
    }
}
