//! Property tests of the edge: every request a client can send (random field values, and any
//! bytes that decode as a request) converts into core types or fails with INVALID_ARGUMENT and a
//! bounded message — never a panic, never an echo of a huge input. Both protocols.

use std::collections::HashMap;

use esrp_server::dm_env::convert::{action_of, create_options, reset_world_scene};
use esrp_server::dm_env::wire::dm_env_rpc::v1 as dm;
use esrp_server::esrp_v1::convert::{reset_of, step_calls};
use esrp_server::proto;
use esrp_server::types::{CreateOptions, PlanCall, StepCall};
use proptest::prelude::*;
use prost::Message;
use tonic::Code;

/// The longest message an error about client input may have: bounded echoes (64 characters
/// and a length) plus the explanation.
const MAX_MESSAGE: usize = 1200;

fn text() -> impl Strategy<Value = String> {
    prop_oneof![
        4 => prop::collection::vec(any::<char>(), 0..24).prop_map(|v| v.into_iter().collect()),
        1 => prop::collection::vec(any::<char>(), 0..5000).prop_map(|v| v.into_iter().collect()),
        1 => Just("esrp-bench-v2/00003".to_owned()),
    ]
}

fn float() -> impl Strategy<Value = f64> {
    prop_oneof![any::<f64>(), Just(f64::NAN), Just(f64::INFINITY), Just(-0.0), -20.0..20.0]
}

fn small_int() -> impl Strategy<Value = i32> {
    prop_oneof![-3..8i32, any::<i32>()]
}

fn create_request() -> impl Strategy<Value = proto::CreateEpisodeRequest> {
    use proto::create_episode_request::Scene;
    let scene = prop_oneof![
        Just(None),
        text().prop_map(|t| Some(Scene::SceneId(t))),
        text().prop_map(|t| Some(Scene::SceneJson(t)))
    ];
    let reward = prop::option::of((float(), float(), float(), float(), float(), float()).prop_map(
        |(success, place, unplace, potential, holding, living)| proto::RewardWeights {
            success: Some(success),
            place: Some(place),
            unplace: Some(unplace),
            potential: Some(potential),
            holding: Some(holding),
            living: Some(living),
        },
    ));
    let sensors = prop::option::of((any::<bool>(), any::<bool>(), any::<bool>(), any::<u32>()).prop_map(
        |(ego_depth, ego_segmentation, current_top_down, resolution)| proto::Sensors {
            ego_depth,
            ego_segmentation,
            current_top_down,
            resolution,
        },
    ));
    (scene, small_int(), any::<u64>(), any::<u32>(), reward, sensors, any::<bool>(), ".{0,260}").prop_map(
        |(scene, split, seed, horizon, reward, sensors, privileged, agent)| proto::CreateEpisodeRequest {
            scene,
            split,
            seed,
            horizon,
            reward,
            sensors,
            privileged,
            agent,
        },
    )
}

fn tensor() -> impl Strategy<Value = dm::Tensor> {
    use dm::tensor::{Payload, *};
    let payload = prop_oneof![
        Just(None),
        prop::collection::vec(small_int(), 0..4).prop_map(|v| Some(Payload::Int32s(Int32Array { array: v }))),
        prop::collection::vec(any::<i64>(), 0..4).prop_map(|v| Some(Payload::Int64s(Int64Array { array: v }))),
        prop::collection::vec(any::<u64>(), 0..3).prop_map(|v| Some(Payload::Uint64s(Uint64Array { array: v }))),
        prop::collection::vec(float(), 0..3).prop_map(|v| Some(Payload::Doubles(DoubleArray { array: v }))),
        prop::collection::vec(any::<bool>(), 0..3).prop_map(|v| Some(Payload::Bools(BoolArray { array: v }))),
        prop::collection::vec(text(), 0..3).prop_map(|v| Some(Payload::Strings(StringArray { array: v }))),
        prop::collection::vec(any::<u8>(), 0..16).prop_map(|v| Some(Payload::Uint8s(Uint8Array { array: v.into() }))),
    ];
    (payload, prop::collection::vec(-2..4i32, 0..3)).prop_map(|(payload, shape)| dm::Tensor { payload, shape })
}

fn settings() -> impl Strategy<Value = HashMap<String, dm::Tensor>> {
    let key = prop_oneof![
        3 => prop::sample::select(vec![
            "scene", "scene_json", "split", "seed", "horizon", "privileged", "resolution", "ego_depth",
            "ego_segmentation", "current_top_down", "reward_success", "reward_potential",
        ])
        .prop_map(str::to_owned),
        1 => text(),
    ];
    prop::collection::hash_map(key, tensor(), 0..6)
}

/// An error about client input: INVALID_ARGUMENT (or NOT_FOUND for an id) with a bounded message.
fn check_refusal(code: Code, message: &str) -> Result<(), TestCaseError> {
    prop_assert!(matches!(code, Code::InvalidArgument | Code::NotFound), "{code:?}: {message}");
    prop_assert!(message.len() <= MAX_MESSAGE, "a {}-byte message: {}", message.len(), &message[..200]);
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn create_requests_convert_or_say_why(request in create_request()) {
        if let Err(e) = CreateOptions::try_from(request) {
            check_refusal(e.code(), &e.to_string())?;
        }
    }

    #[test]
    fn step_requests_convert_or_say_why(
        steps in prop::collection::vec((text(), small_int(), any::<bool>()), 0..4),
    ) {
        let requests = steps
            .into_iter()
            .map(|(episode_id, action, include_goal)| proto::StepRequest { episode_id, action, include_goal })
            .collect();
        if let Err(e) = step_calls(requests) {
            check_refusal(e.code(), &e.to_string())?;
        }
    }

    #[test]
    fn dm_env_settings_and_actions_convert_or_say_why(settings in settings(), action in tensor(), uid in 0..3u64) {
        if let Err(e) = create_options(settings.clone()) {
            check_refusal(e.code(), &e.to_string())?;
        }
        if let Err(e) = reset_world_scene(settings) {
            check_refusal(e.code(), &e.to_string())?;
        }
        if let Err(e) = action_of(&HashMap::from([(uid, action)])) {
            check_refusal(e.code(), &e.to_string())?;
        }
    }

    /// Any bytes that decode as a request convert without a panic.
    #[test]
    fn decoded_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        if let Ok(r) = proto::CreateEpisodeRequest::decode(&bytes[..]) {
            let _ = CreateOptions::try_from(r);
        }
        if let Ok(r) = proto::StepRequest::decode(&bytes[..]) {
            let _ = StepCall::try_from(r);
        }
        if let Ok(r) = proto::StepBatchRequest::decode(&bytes[..]) {
            let _ = step_calls(r.steps);
        }
        if let Ok(r) = proto::ResetRequest::decode(&bytes[..]) {
            let _ = reset_of(r);
        }
        if let Ok(r) = proto::PlanActionsRequest::decode(&bytes[..]) {
            let _ = PlanCall::from(r);
        }
        if let Ok(r) = dm::CreateWorldRequest::decode(&bytes[..]) {
            let _ = create_options(r.settings);
        }
        if let Ok(r) = dm::StepRequest::decode(&bytes[..]) {
            let _ = action_of(&r.actions);
        }
    }
}
