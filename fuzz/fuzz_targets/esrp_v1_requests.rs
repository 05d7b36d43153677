//! Arbitrary bytes as an esrp.v1 request (the first byte picks which: CreateEpisode, Step,
//! StepBatch, Reset, PlanActions), pushed through the conversions the handlers use
//! (`esrp_server::esrp_v1::convert`). Each must convert or refuse with INVALID_ARGUMENT or
//! NOT_FOUND and a bounded message (client input is echoed 64 characters at most), never
//! panic; what converts must hold what the request said.

#![no_main]

use esrp_server::episodes::{CreateOptions, PlanCall, StepCall};
use esrp_server::esrp_v1::convert::{reset_of, step_calls};
use esrp_server::proto;
use libfuzzer_sys::fuzz_target;
use prost::Message;

#[path = "common/refusal.rs"]
mod refusal;
use refusal::refused;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, bytes)) = data.split_first() else { return };
    match kind % 5 {
        0 => {
            let Ok(request) = proto::CreateEpisodeRequest::decode(bytes) else { return };
            if let Err(e) = CreateOptions::try_from(request) {
                refused(e.code(), &e.to_string());
            }
        }
        1 => {
            let Ok(request) = proto::StepRequest::decode(bytes) else { return };
            let id = request.episode_id.clone();
            match StepCall::try_from(request) {
                Ok(call) => assert_eq!(call.episode.as_str(), id, "the step names its episode"),
                Err(e) => refused(e.code(), &e.to_string()),
            }
        }
        2 => {
            let Ok(request) = proto::StepBatchRequest::decode(bytes) else { return };
            let count = request.steps.len();
            match step_calls(request.steps) {
                Ok(calls) => assert_eq!(calls.len(), count, "one call per step"),
                Err(e) => refused(e.code(), &e.to_string()),
            }
        }
        3 => {
            let Ok(request) = proto::ResetRequest::decode(bytes) else { return };
            let id = request.episode_id.clone();
            let (episode, _) = reset_of(request);
            assert_eq!(episode.as_str(), id, "the reset names its episode");
        }
        _ => {
            let Ok(request) = proto::PlanActionsRequest::decode(bytes) else { return };
            let _ = PlanCall::from(request);
        }
    }
});
