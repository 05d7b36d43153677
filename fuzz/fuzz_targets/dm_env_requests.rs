//! Arbitrary bytes as a dm_env_rpc `EnvironmentRequest`, its settings and actions pushed through
//! the conversions the handlers use (`esrp_server::dm_env::convert`): CreateWorld's and
//! ResetWorld's settings, Step's actions, JoinWorld's and Reset's (refused) settings. Each must
//! convert or refuse with INVALID_ARGUMENT or NOT_FOUND and a bounded message, never panic.

#![no_main]

use esrp_server::dm_env::convert::{action_of, create_options, no_settings, reset_world_scene};
use esrp_server::dm_env::wire::dm_env_rpc::v1 as dm;
use libfuzzer_sys::fuzz_target;
use prost::Message;

#[path = "common/refusal.rs"]
mod refusal;
use refusal::refused;

fuzz_target!(|data: &[u8]| {
    use dm::environment_request::Payload;
    let Ok(request) = dm::EnvironmentRequest::decode(data) else { return };
    let result = match request.payload {
        Some(Payload::CreateWorld(r)) => create_options(r.settings).map(drop),
        Some(Payload::ResetWorld(r)) => reset_world_scene(r.settings).map(drop),
        Some(Payload::Step(r)) => action_of(&r.actions).map(drop),
        Some(Payload::JoinWorld(r)) => no_settings("JoinWorld", &r.settings),
        Some(Payload::Reset(r)) => no_settings("Reset", &r.settings),
        _ => Ok(()),
    };
    if let Err(e) = result {
        refused(e.code(), &e.to_string());
    }
});
