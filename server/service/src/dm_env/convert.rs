//! Conversions between `dm_env_rpc.v1` tensors and the core types, at the edge: settings
//! into [`CreateOptions`], the action tensor into an [`Action`], a world's [`SensorConfig`]
//! into its specs, and an [`Observation`] into tensors. Image pixels move as `Bytes` from the
//! render readback into the tensors, never copied; depth and segmentation move as they are.

use std::collections::HashMap;

use esrp_core::{Action, Split};

use esrp_proto::dm_env_rpc::v1 as dm;
use esrp_proto::dm_env_rpc::v1::tensor::Payload as Elements;

use super::error::DmEnvError;
use crate::error::ServiceError;
use crate::quote::quoted;
use crate::types::{CreateOptions, ElementType, Observation, SceneChoice, SensorConfig, SensorRequest};

/// The uid of the only action.
pub const ACTION_UID: u64 = 1;
/// The action's name in the specs.
pub const ACTION_NAME: &str = "action";
/// The largest action code.
pub const MAX_ACTION: i32 = 5;

/// The element type of `tensor`, for messages.
fn element_type(tensor: &dm::Tensor) -> &'static str {
    match &tensor.payload {
        None => "no payload",
        Some(Elements::Floats(_)) => "FLOAT",
        Some(Elements::Doubles(_)) => "DOUBLE",
        Some(Elements::Int8s(_)) => "INT8",
        Some(Elements::Int32s(_)) => "INT32",
        Some(Elements::Int64s(_)) => "INT64",
        Some(Elements::Uint8s(_)) => "UINT8",
        Some(Elements::Uint32s(_)) => "UINT32",
        Some(Elements::Uint64s(_)) => "UINT64",
        Some(Elements::Bools(_)) => "BOOL",
        Some(Elements::Strings(_)) => "STRING",
        Some(Elements::Protos(_)) => "PROTO",
    }
}

fn element_count(tensor: &dm::Tensor) -> usize {
    match &tensor.payload {
        None => 0,
        Some(Elements::Floats(a)) => a.array.len(),
        Some(Elements::Doubles(a)) => a.array.len(),
        Some(Elements::Int8s(a)) => a.array.len(),
        Some(Elements::Int32s(a)) => a.array.len(),
        Some(Elements::Int64s(a)) => a.array.len(),
        Some(Elements::Uint8s(a)) => a.array.len(),
        Some(Elements::Uint32s(a)) => a.array.len(),
        Some(Elements::Uint64s(a)) => a.array.len(),
        Some(Elements::Bools(a)) => a.array.len(),
        Some(Elements::Strings(a)) => a.array.len(),
        Some(Elements::Protos(a)) => a.array.len(),
    }
}

/// Checks that the setting `name` is a single value (shape `[]`, or only 1 and -1).
fn check_scalar_setting(name: &str, tensor: &dm::Tensor) -> Result<(), DmEnvError> {
    let count = element_count(tensor);
    if count != 1 || tensor.shape.iter().any(|&d| d != 1 && d != -1) {
        return Err(DmEnvError::InvalidSetting(format!(
            "setting {name}: expected a single value, got {count} elements of shape {:?}",
            tensor.shape
        )));
    }
    Ok(())
}

fn string_setting(name: &str, tensor: &dm::Tensor) -> Result<String, DmEnvError> {
    check_scalar_setting(name, tensor)?;
    match &tensor.payload {
        Some(Elements::Strings(a)) => Ok(a.array[0].clone()),
        _ => {
            Err(DmEnvError::InvalidSetting(format!("setting {name}: expected a STRING, got {}", element_type(tensor))))
        }
    }
}

/// The `scene` setting: a scene id, never empty (leave the setting out for the default).
fn scene_setting(tensor: &dm::Tensor) -> Result<String, DmEnvError> {
    let id = string_setting("scene", tensor)?;
    if id.is_empty() {
        return Err(DmEnvError::InvalidSetting(
            "setting scene: the scene id is empty: give a served scene's id, or leave the setting out".into(),
        ));
    }
    Ok(id)
}

fn bool_setting(name: &str, tensor: &dm::Tensor) -> Result<bool, DmEnvError> {
    check_scalar_setting(name, tensor)?;
    match &tensor.payload {
        Some(Elements::Bools(a)) => Ok(a.array[0]),
        _ => Err(DmEnvError::InvalidSetting(format!("setting {name}: expected a BOOL, got {}", element_type(tensor)))),
    }
}

/// A non-negative integer setting of any integer element type.
fn integer_setting(name: &str, tensor: &dm::Tensor) -> Result<u64, DmEnvError> {
    check_scalar_setting(name, tensor)?;
    let value: i128 = match &tensor.payload {
        Some(Elements::Int8s(a)) => i128::from(a.array[0] as i8),
        Some(Elements::Int32s(a)) => i128::from(a.array[0]),
        Some(Elements::Int64s(a)) => i128::from(a.array[0]),
        Some(Elements::Uint8s(a)) => i128::from(a.array[0]),
        Some(Elements::Uint32s(a)) => i128::from(a.array[0]),
        Some(Elements::Uint64s(a)) => i128::from(a.array[0]),
        _ => {
            return Err(DmEnvError::InvalidSetting(format!(
                "setting {name}: expected an integer, got {}",
                element_type(tensor)
            )));
        }
    };
    u64::try_from(value)
        .map_err(|_| DmEnvError::InvalidSetting(format!("setting {name}: {value} is negative: use 0 or more")))
}

fn u32_setting(name: &str, tensor: &dm::Tensor) -> Result<u32, DmEnvError> {
    let value = integer_setting(name, tensor)?;
    u32::try_from(value).map_err(|_| DmEnvError::InvalidSetting(format!("setting {name}: {value} is too large")))
}

/// Settings sorted by name, so that the first bad one reported does not depend on hash order.
fn sorted(settings: HashMap<String, dm::Tensor>) -> Vec<(String, dm::Tensor)> {
    let mut settings: Vec<(String, dm::Tensor)> = settings.into_iter().collect();
    settings.sort_by(|a, b| a.0.cmp(&b.0));
    settings
}

/// The CreateWorld setting names.
pub const CREATE_WORLD_SETTINGS: [&str; 9] =
    ["scene", "split", "seed", "horizon", "resolution", "ego_depth", "ego_segmentation", "current_top_down", "agent"];

/// The episode a CreateWorld's settings ask for.
pub fn create_options(settings: HashMap<String, dm::Tensor>) -> Result<CreateOptions, DmEnvError> {
    let (mut scene, mut split, mut seed, mut horizon, mut agent) = (None, None, 0, None, None);
    let mut sensors = SensorRequest::default();
    for (name, value) in sorted(settings) {
        match name.as_str() {
            "scene" => scene = Some(scene_setting(&value)?),
            "agent" => agent = Some(string_setting(&name, &value)?).filter(|a| !a.is_empty()),
            "split" => {
                let name = string_setting(&name, &value)?;
                split = Some(name.parse::<Split>().map_err(|_| {
                    DmEnvError::InvalidSetting(format!(
                        "setting split: {} is not a split: use \"train\", \"test\", \"challenge\" or \"minival\"",
                        quoted(&name)
                    ))
                })?)
            }
            "seed" => seed = integer_setting(&name, &value)?,
            "horizon" => horizon = Some(u32_setting(&name, &value)?).filter(|&h| h != 0),
            "resolution" => sensors.resolution = Some(u32_setting(&name, &value)?).filter(|&r| r != 0),
            "ego_depth" => sensors.depth = bool_setting(&name, &value)?,
            "ego_segmentation" => sensors.segmentation = bool_setting(&name, &value)?,
            "current_top_down" => sensors.current_top_down = bool_setting(&name, &value)?,
            other => {
                return Err(DmEnvError::InvalidSetting(format!(
                    "unknown CreateWorld setting {}: the settings are {}",
                    quoted(other),
                    CREATE_WORLD_SETTINGS.join(", ")
                )));
            }
        }
    }
    let scene = match scene {
        Some(id) => SceneChoice::SceneId(id),
        None => SceneChoice::FromSplit { split, seed },
    };
    Ok(CreateOptions {
        scene,
        sensors,
        horizon,
        reward: Default::default(),
        privileged: false,
        agent,
        keep_record: false,
    })
}

/// The new scene a ResetWorld's settings ask for, if any.
pub fn reset_world_scene(settings: HashMap<String, dm::Tensor>) -> Result<Option<SceneChoice>, DmEnvError> {
    let mut scene = None;
    for (name, value) in sorted(settings) {
        match name.as_str() {
            "scene" => scene = Some(scene_setting(&value)?),
            other => {
                return Err(DmEnvError::InvalidSetting(format!(
                    "unknown ResetWorld setting {}: the only one is \"scene\"",
                    quoted(other)
                )));
            }
        }
    }
    Ok(scene.map(SceneChoice::SceneId))
}

/// Fails on any setting: for the requests that take none.
pub fn no_settings(request: &str, settings: &HashMap<String, dm::Tensor>) -> Result<(), DmEnvError> {
    match sorted(settings.clone()).first() {
        None => Ok(()),
        Some((name, _)) => Err(DmEnvError::InvalidSetting(format!(
            "unknown {request} setting {}: {request} takes no settings",
            quoted(name)
        ))),
    }
}

// Specs and observations.

fn data_type(element_type: ElementType) -> dm::DataType {
    match element_type {
        ElementType::Uint8 => dm::DataType::Uint8,
        ElementType::Float32 => dm::DataType::Float,
        ElementType::Uint32 => dm::DataType::Uint32,
        ElementType::Bool => dm::DataType::Bool,
    }
}

/// The specs of a world whose episodes have `sensors`, and the observation names by uid - 1.
pub fn specs_of(sensors: &SensorConfig) -> (dm::ActionObservationSpecs, Vec<String>) {
    let mut observations: Vec<dm::TensorSpec> = sensors
        .observation_spec()
        .into_iter()
        .map(|array| dm::TensorSpec {
            name: array.name.to_owned(),
            shape: array.shape.iter().map(|&d| d as i32).collect(),
            dtype: data_type(array.element_type) as i32,
            min: None,
            max: None,
        })
        .collect();
    let double = |name: &str, bounds: Option<(f64, f64)>| dm::TensorSpec {
        name: name.to_owned(),
        shape: Vec::new(),
        dtype: dm::DataType::Double as i32,
        min: bounds.map(|b| doubles_value(b.0)),
        max: bounds.map(|b| doubles_value(b.1)),
    };
    observations.push(double("reward", None));
    observations.push(double("discount", Some((0.0, 1.0))));
    let names = observations.iter().map(|s| s.name.clone()).collect();
    let action = dm::TensorSpec {
        name: ACTION_NAME.to_owned(),
        shape: Vec::new(),
        dtype: dm::DataType::Int32 as i32,
        min: Some(int32s_value(0)),
        max: Some(int32s_value(MAX_ACTION)),
    };
    let specs = dm::ActionObservationSpecs {
        actions: HashMap::from([(ACTION_UID, action)]),
        observations: observations.into_iter().enumerate().map(|(i, s)| (i as u64 + 1, s)).collect(),
    };
    (specs, names)
}

fn doubles_value(value: f64) -> dm::tensor_spec::Value {
    dm::tensor_spec::Value {
        payload: Some(dm::tensor_spec::value::Payload::Doubles(dm::tensor::DoubleArray { array: vec![value] })),
    }
}

fn int32s_value(value: i32) -> dm::tensor_spec::Value {
    dm::tensor_spec::Value {
        payload: Some(dm::tensor_spec::value::Payload::Int32s(dm::tensor::Int32Array { array: vec![value] })),
    }
}

pub(crate) fn tensor(shape: Vec<i32>, elements: Elements) -> dm::Tensor {
    dm::Tensor { shape, payload: Some(elements) }
}

fn image_tensor(rgb: bytes::Bytes, resolution: u32) -> dm::Tensor {
    let side = resolution as i32;
    tensor(vec![side, side, 3], Elements::Uint8s(dm::tensor::Uint8Array { array: rgb }))
}

/// The observation `name` of a step, moved out of `observation` (each name is asked for
/// once), or the reward and discount.
pub fn observation_tensor(
    name: &str,
    observation: &mut Observation,
    reward: f64,
    discount: f64,
) -> Result<dm::Tensor, DmEnvError> {
    let side = observation.resolution as i32;
    let found = match name {
        "ego_rgb" => Some(image_tensor(std::mem::take(&mut observation.ego_rgb), observation.resolution)),
        "goal_rgb" => observation.goal_rgb.take().map(|g| image_tensor(g, observation.resolution)),
        "current_top_down" => observation.current_top_down.take().map(|t| image_tensor(t, observation.resolution)),
        "grasping" => {
            Some(tensor(Vec::new(), Elements::Bools(dm::tensor::BoolArray { array: vec![observation.grasping] })))
        }
        "ego_depth" => observation
            .depth
            .take()
            .map(|array| tensor(vec![side, side], Elements::Floats(dm::tensor::FloatArray { array }))),
        "ego_segmentation" => observation
            .segmentation
            .take()
            .map(|array| tensor(vec![side, side], Elements::Uint32s(dm::tensor::Uint32Array { array }))),
        "reward" => Some(tensor(Vec::new(), Elements::Doubles(dm::tensor::DoubleArray { array: vec![reward] }))),
        "discount" => Some(tensor(Vec::new(), Elements::Doubles(dm::tensor::DoubleArray { array: vec![discount] }))),
        _ => None,
    };
    found.ok_or_else(|| ServiceError::Internal(format!("the episode returned no {name} observation")).into())
}

/// The action of a running step: uid 1, an INT32 scalar in 0..=5.
pub fn action_of(actions: &HashMap<u64, dm::Tensor>) -> Result<Action, DmEnvError> {
    if let Some(uid) = actions.keys().find(|&&uid| uid != ACTION_UID) {
        return Err(DmEnvError::InvalidAction(format!(
            "unknown action uid {uid}: the only action is uid {ACTION_UID} ({ACTION_NAME:?})"
        )));
    }
    let Some(action) = actions.get(&ACTION_UID) else {
        return Err(DmEnvError::InvalidAction(format!(
            "the action (uid {ACTION_UID}) is required on every step of a running sequence: send an INT32 scalar 0..=5"
        )));
    };
    let Some(Elements::Int32s(values)) = &action.payload else {
        return Err(DmEnvError::InvalidAction(format!(
            "action: expected an INT32 tensor, got {}",
            element_type(action)
        )));
    };
    if !action.shape.is_empty() {
        return Err(DmEnvError::InvalidAction(format!(
            "action: expected a scalar (shape []), got shape {:?}",
            action.shape
        )));
    }
    let [value] = values.array[..] else {
        return Err(DmEnvError::InvalidAction(format!("action: expected one element, got {}", values.array.len())));
    };
    if !(0..=MAX_ACTION).contains(&value) {
        return Err(DmEnvError::InvalidAction(format!(
            "action: {value} is out of range: use 0 move_forward, 1 move_backward, 2 turn_left, 3 turn_right, 4 fetch or 5 release"
        )));
    }
    Action::from_code(i64::from(value)).map_err(|e| DmEnvError::InvalidAction(format!("action: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn int64(value: i64) -> dm::Tensor {
        tensor(Vec::new(), Elements::Int64s(dm::tensor::Int64Array { array: vec![value] }))
    }

    fn int32(shape: Vec<i32>, values: Vec<i32>) -> dm::Tensor {
        tensor(shape, Elements::Int32s(dm::tensor::Int32Array { array: values }))
    }

    fn string(value: &str) -> dm::Tensor {
        tensor(Vec::new(), Elements::Strings(dm::tensor::StringArray { array: vec![value.to_owned()] }))
    }

    /// Parses `settings`; the request's summary or the error's message must contain `expected`.
    fn check_settings(settings: Vec<(&str, dm::Tensor)>, expected: &str) {
        let settings = settings.into_iter().map(|(k, v)| (k.to_owned(), v)).collect();
        let got = match create_options(settings) {
            Ok(r) => format!("scene={:?} horizon={:?} sensors={:?}", r.scene, r.horizon, r.sensors),
            Err(e) => e.to_string(),
        };
        assert!(got.contains(expected), "{got:?} does not contain {expected:?}");
    }

    #[test]
    fn create_world_settings_map_to_the_native_request() {
        check_settings(vec![], "scene=FromSplit { split: None, seed: 0 } horizon=None");
        check_settings(vec![("scene", string("a/1"))], "SceneId(\"a/1\")");
        check_settings(
            vec![("split", string("train")), ("seed", int64(7))],
            "FromSplit { split: Some(Train), seed: 7 }",
        );
        check_settings(vec![("horizon", int32(vec![], vec![9]))], "horizon=Some(9)");
        check_settings(vec![("resolution", int64(64))], "resolution: Some(64)");
        check_settings(vec![("seed", int64(-1))], "setting seed: -1 is negative");
        check_settings(vec![("split", string("dev"))], "not a split");
        check_settings(vec![("scene", int64(3))], "setting scene: expected a STRING, got INT64");
        // An explicit empty scene is not the default scene.
        check_settings(vec![("scene", string(""))], "setting scene: the scene id is empty");
        let reset = reset_world_scene([("scene".to_owned(), string(""))].into());
        assert!(reset.unwrap_err().to_string().contains("the scene id is empty"));
        check_settings(vec![("seed", int32(vec![2], vec![1, 2]))], "expected a single value, got 2 elements");
        check_settings(vec![("zeta", int64(1)), ("alpha", int64(1))], "unknown CreateWorld setting \"alpha\"");
    }

    fn check_action(tensor: Option<dm::Tensor>, expected: Result<Action, &str>) {
        let actions = tensor.map(|t| HashMap::from([(ACTION_UID, t)])).unwrap_or_default();
        match (action_of(&actions), expected) {
            (Ok(got), Ok(want)) => assert_eq!(got, want),
            (Err(e), Err(want)) => assert!(e.to_string().contains(want), "{e} does not contain {want:?}"),
            (got, want) => panic!("got {got:?}, expected {want:?}"),
        }
    }

    #[test]
    fn the_action_is_an_int32_scalar_from_0_to_5() {
        check_action(Some(int32(vec![], vec![0])), Ok(Action::MoveForward));
        check_action(Some(int32(vec![], vec![5])), Ok(Action::Release));
        check_action(Some(int32(vec![], vec![6])), Err("6 is out of range"));
        check_action(Some(int32(vec![], vec![-1])), Err("-1 is out of range"));
        check_action(Some(int32(vec![1], vec![1])), Err("expected a scalar"));
        check_action(Some(int32(vec![], vec![1, 2])), Err("expected one element, got 2"));
        check_action(Some(int64(1)), Err("expected an INT32 tensor, got INT64"));
        check_action(None, Err("is required"));
        let extra = HashMap::from([(ACTION_UID, int32(vec![], vec![1])), (7, int64(1))]);
        assert!(action_of(&extra).unwrap_err().to_string().contains("unknown action uid 7"));
    }

    #[test]
    fn specs_number_the_native_observations_then_reward_and_discount() {
        let sensors = SensorConfig { depth: true, segmentation: false, current_top_down: false, resolution: 8 };
        let (specs, names) = specs_of(&sensors);
        assert_eq!(names, ["ego_rgb", "goal_rgb", "grasping", "ego_depth", "reward", "discount"]);
        assert_eq!(specs.observations[&1].shape, [8, 8, 3]);
        assert_eq!(specs.observations[&4].dtype, dm::DataType::Float as i32);
        assert_eq!(specs.observations[&6].max, Some(doubles_value(1.0)));
        assert_eq!(specs.actions[&ACTION_UID].max, Some(int32s_value(MAX_ACTION)));
        // Every element type has its dm_env_rpc type (an exhaustive match, checked by the
        // compiler): no observation can lack one.
        for element_type in [ElementType::Uint8, ElementType::Float32, ElementType::Uint32, ElementType::Bool] {
            assert_ne!(data_type(element_type), dm::DataType::InvalidDataType);
        }
    }

    #[test]
    fn observations_become_tensors_without_copying_pixels() {
        let rgb = bytes::Bytes::from(vec![9u8; 2 * 2 * 3]);
        let mut observation =
            Observation { resolution: 2, ego_rgb: rgb.clone(), depth: Some(vec![0.5; 4]), ..Default::default() };
        let ego = observation_tensor("ego_rgb", &mut observation, 0.0, 1.0).unwrap();
        assert_eq!(ego.shape, [2, 2, 3]);
        let Some(Elements::Uint8s(pixels)) = ego.payload else { panic!("ego_rgb is UINT8") };
        assert_eq!(pixels.array.as_ptr(), rgb.as_ptr(), "the RGB buffer is shared, not copied");
        let depth = observation_tensor("ego_depth", &mut observation, 0.0, 1.0).unwrap();
        assert_eq!(depth.payload, Some(Elements::Floats(dm::tensor::FloatArray { array: vec![0.5; 4] })));
        let reward = observation_tensor("reward", &mut observation, 2.5, 1.0).unwrap();
        assert_eq!(reward.payload, Some(Elements::Doubles(dm::tensor::DoubleArray { array: vec![2.5] })));
        let missing = observation_tensor("goal_rgb", &mut observation, 0.0, 1.0).unwrap_err();
        assert!(missing.to_string().contains("no goal_rgb observation"), "{missing}");
    }
}
