//! The 3D-FRONT house JSON and 3D-FUTURE's `model_info.json`, as serde reads them.

use serde::Deserialize;

#[derive(Debug, Deserialize)]
pub(super) struct House {
    #[serde(default)]
    pub(super) furniture: Vec<Furniture>,
    #[serde(default)]
    pub(super) mesh: Vec<ArchMesh>,
    pub(super) scene: HouseScene,
}

#[derive(Debug, Deserialize)]
pub(super) struct Furniture {
    pub(super) uid: String,
    #[serde(default)]
    pub(super) jid: Option<String>,
    #[serde(default)]
    pub(super) title: Option<String>,
    #[serde(default)]
    pub(super) category: Option<String>,
    #[serde(default)]
    pub(super) bbox: Option<Vec<f64>>,
}

#[derive(Debug, Deserialize)]
pub(super) struct ArchMesh {
    pub(super) uid: String,
    #[serde(rename = "type", default)]
    pub(super) kind: String,
    #[serde(default)]
    pub(super) xyz: Vec<f64>,
    #[serde(default)]
    pub(super) faces: Vec<u32>,
}

#[derive(Debug, Deserialize)]
pub(super) struct HouseScene {
    #[serde(default)]
    pub(super) room: Vec<FrontRoom>,
}

#[derive(Debug, Deserialize)]
pub(super) struct FrontRoom {
    #[serde(rename = "type", default)]
    pub(super) room_type: String,
    #[serde(rename = "instanceid", default)]
    pub(super) instance_id: String,
    #[serde(default)]
    pub(super) children: Vec<Child>,
}

#[derive(Clone, Debug, Deserialize)]
pub(super) struct Child {
    #[serde(rename = "ref")]
    pub(super) reference: String,
    #[serde(default)]
    pub(super) pos: [f64; 3],
    #[serde(default = "identity_quaternion")]
    pub(super) rot: [f64; 4],
    #[serde(default = "unit_scale")]
    pub(super) scale: [f64; 3],
}

pub(super) fn identity_quaternion() -> [f64; 4] {
    [0.0, 0.0, 0.0, 1.0]
}

pub(super) fn unit_scale() -> [f64; 3] {
    [1.0; 3]
}

#[derive(Debug, Deserialize)]
pub(super) struct ModelInfo {
    pub(super) model_id: String,
    #[serde(rename = "super-category", default)]
    pub(super) super_category: Option<String>,
    #[serde(default)]
    pub(super) category: Option<String>,
}
