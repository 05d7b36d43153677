//! The service's errors: [`ServiceError`] for calls on episodes, with its one exhaustive
//! mapping to gRPC status codes. (Why the server could not start is `serve::ServeError`.)

use esrp_core::Split;
use tonic::{Code, Status};

use crate::quote::{MAX_QUOTED_MESSAGE, bound_message, bounded, quoted};
use crate::records::AlreadyPlayed;
use crate::types::EpisodeId;

/// Why a call failed.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A request field is malformed.
    #[error("{0}")]
    InvalidArgument(String),
    /// An action code is not one of SPEC §3 (`at` locates the step in its call).
    #[error("{at}.action: {error}")]
    InvalidAction {
        /// Where: `step`, or `steps[3]` in a batch.
        at: String,
        /// What was wrong.
        error: esrp_core::UnknownAction,
    },
    /// A batch steps (or resets) one episode twice.
    #[error(
        "{at}: episode {} appears twice in one batch: send one step or reset per episode",
        bounded(.episode.as_str())
    )]
    DuplicateStep {
        /// Where: `steps[3]`, `resets[0]`.
        at: String,
        /// The episode.
        episode: EpisodeId,
    },
    /// A resolution out of range.
    #[error("sensors.resolution {resolution} is out of range: use 16 to {max} pixels (0 means 128)")]
    InvalidResolution {
        /// The resolution asked for.
        resolution: u32,
        /// The largest allowed.
        max: u32,
    },
    /// The split chosen has no scenes in the served dataset.
    #[error("the served dataset has no {} scenes: choose another split or a scene_id", .0.as_str())]
    EmptySplit(Split),
    /// The episode id is unknown or closed.
    #[error("no episode {}: it never existed, was closed, or was closed after being idle", quoted(.0.as_str()))]
    UnknownEpisode(EpisodeId),
    /// The scene id is not in the served dataset.
    #[error("no scene {} in the served dataset: ListScenes lists the ids", quoted(.0))]
    UnknownScene(String),
    /// A step of an episode that has ended (`at` locates the step in its call).
    #[error("{at}: episode {} has ended after {steps} steps: Reset it or create a new one", bounded(.episode.as_str()))]
    EpisodeOver {
        /// Where: `step`, or `steps[3]` in a batch.
        at: String,
        /// The episode.
        episode: EpisodeId,
        /// The steps it took.
        steps: u32,
    },
    /// The simulator refused (an ended episode, a configuration it cannot run).
    #[error("{0}")]
    Simulator(esrp_core::EpisodeError),
    /// The call needs a privileged episode.
    #[error(
        "episode {} was not created with privileged = true: GetPrivilegedState and PlanActions are for privileged episodes only",
        bounded(.0.as_str())
    )]
    NotPrivileged(EpisodeId),
    /// PlanActions found no plan within its time budget.
    #[error(
        "the planner found no plan within its budget of {budget_ms} ms: ask with a larger budget_ms (the server caps it at --max-plan-ms)"
    )]
    PlanDeadline {
        /// The budget the call had.
        budget_ms: u64,
    },
    /// PlanActions waited its whole time budget for a planner thread: every one was planning for
    /// other calls, so this call planned nothing.
    #[error(
        "no planner thread came free within the budget of {budget_ms} ms: all {threads} (--planner-threads) \
         were planning for other calls, so this call planned nothing; call again, with a larger budget_ms, \
         or start the server with more --planner-threads"
    )]
    PlannersBusy {
        /// The budget the call had.
        budget_ms: u64,
        /// Plans computed at once (`--planner-threads`).
        threads: usize,
    },
    /// The server holds its maximum of live episodes.
    #[error("the server holds its maximum of {max} live episodes: close some (CloseEpisode) or raise --max-episodes")]
    TooManyEpisodes {
        /// `--max-episodes`.
        max: usize,
    },
    /// A batch of more steps (and resets) than `--max-batch`.
    #[error("a batch of {steps} steps and resets exceeds the limit of {max} (--max-batch)")]
    BatchTooLarge {
        /// Steps and resets in the batch.
        steps: usize,
        /// `--max-batch`.
        max: usize,
    },
    /// The answer to one step would not fit in a message.
    #[error(
        "the answer to this step would take about {:.1} MB, over the {:.1} MB message limit \
         (--max-message-bytes): ask for fewer sensors, a smaller resolution or no goal image",
        *.bytes as f64 / 1e6, *.max as f64 / 1e6
    )]
    StepAnswerTooLarge {
        /// An upper bound of the answer's size, bytes.
        bytes: usize,
        /// `--max-message-bytes`.
        max: usize,
    },
    /// The answer to a create (or a reset: the first observation with the goal image) would
    /// not fit in a message.
    #[error(
        "the answer to this create would take about {:.1} MB (the first observation and the goal image), \
         over the {:.1} MB message limit (--max-message-bytes): ask for fewer sensors or a smaller resolution",
        *.bytes as f64 / 1e6, *.max as f64 / 1e6
    )]
    CreateAnswerTooLarge {
        /// An upper bound of the answer's size, bytes.
        bytes: usize,
        /// `--max-message-bytes`.
        max: usize,
    },
    /// The answer to a batch would not fit in a message.
    #[error(
        "the answer to these {steps} steps would take about {:.1} MB, over the {:.1} MB message limit \
         (--max-message-bytes): send fewer steps per call, or ask for goal images less often",
        *.bytes as f64 / 1e6, *.max as f64 / 1e6
    )]
    BatchAnswerTooLarge {
        /// Steps in the batch.
        steps: usize,
        /// An upper bound of the answer's size, bytes.
        bytes: usize,
        /// `--max-message-bytes`.
        max: usize,
    },
    /// The caller's role does not allow the call; the message names the role and what it lacks.
    #[error("{0}")]
    Denied(String),
    /// An episode of another token, named by a caller that is not an admin.
    #[error(
        "episode {} belongs to another token: {caller} may use only the episodes it created",
        bounded(.episode.as_str())
    )]
    NotYours {
        /// The episode.
        episode: EpisodeId,
        /// The caller, described (`token "bob" (role agent)`).
        caller: String,
    },
    /// A token's quota is used up.
    #[error("{caller} already has {limit} {what} open, its quota ({quota} in the token file): close one first")]
    Quota {
        /// The caller, described.
        caller: String,
        /// `live episodes` or `streams`.
        what: &'static str,
        /// The quota's name: `max_episodes` or `max_streams`.
        quota: &'static str,
        /// The quota.
        limit: usize,
    },
    /// A second attempt at a challenge scene.
    #[error(transparent)]
    AlreadyPlayed(#[from] AlreadyPlayed),
    /// Records asked of a server that keeps none.
    #[error("this server keeps no records: start it with --records DIR")]
    NoRecords,
    /// A record that a records file does not hold.
    #[error("token {}'s records have no record {index}", quoted(.token))]
    UnknownRecord {
        /// The file's token.
        token: String,
        /// The record's place in it.
        index: usize,
    },
    /// A counted attempt whose claim could not be journaled (the records folder cannot be
    /// written): refused, and not counted, rather than played without a trace.
    #[error(
        "this attempt cannot be recorded ({0}), so it was not started and is not counted: try again once the \
         server's records folder can be written"
    )]
    NotRecordable(String),
    /// Rendering failed.
    #[error("rendering failed: {0}")]
    Render(String),
    /// A bug or an unexpected failure.
    #[error("internal error: {0}")]
    Internal(String),
}

impl ServiceError {
    /// Its gRPC status code: the one mapping, for every protocol.
    pub fn code(&self) -> Code {
        match self {
            ServiceError::InvalidArgument(_)
            | ServiceError::InvalidAction { .. }
            | ServiceError::DuplicateStep { .. }
            | ServiceError::InvalidResolution { .. }
            | ServiceError::EmptySplit(_) => Code::InvalidArgument,
            ServiceError::UnknownEpisode(_) | ServiceError::UnknownScene(_) | ServiceError::UnknownRecord { .. } => {
                Code::NotFound
            }
            ServiceError::NoRecords => Code::FailedPrecondition,
            ServiceError::EpisodeOver { .. } => Code::FailedPrecondition,
            ServiceError::Simulator(e) => match e {
                esrp_core::EpisodeError::Finished { .. } => Code::FailedPrecondition,
                esrp_core::EpisodeError::InvalidConfig { .. } => Code::InvalidArgument,
                esrp_core::EpisodeError::Failed { .. } => Code::Internal,
            },
            ServiceError::NotPrivileged(_) | ServiceError::Denied(_) | ServiceError::NotYours { .. } => {
                Code::PermissionDenied
            }
            ServiceError::AlreadyPlayed(_) => Code::FailedPrecondition,
            ServiceError::PlanDeadline { .. } | ServiceError::PlannersBusy { .. } => Code::DeadlineExceeded,
            ServiceError::TooManyEpisodes { .. }
            | ServiceError::BatchTooLarge { .. }
            | ServiceError::StepAnswerTooLarge { .. }
            | ServiceError::CreateAnswerTooLarge { .. }
            | ServiceError::BatchAnswerTooLarge { .. }
            | ServiceError::Quota { .. } => Code::ResourceExhausted,
            ServiceError::NotRecordable(_) => Code::Unavailable,
            ServiceError::Render(_) | ServiceError::Internal(_) => Code::Internal,
        }
    }
}

impl From<ServiceError> for Status {
    fn from(error: ServiceError) -> Status {
        Status::new(error.code(), error.to_string())
    }
}

impl From<esrp_core::SceneError> for ServiceError {
    fn from(e: esrp_core::SceneError) -> Self {
        // A scene error may quote the client's JSON (a key, a string): bound the whole message.
        ServiceError::InvalidArgument(format!("invalid scene: {}", bound_message(&e.to_string(), MAX_QUOTED_MESSAGE)))
    }
}

impl From<esrp_core::EpisodeError> for ServiceError {
    fn from(e: esrp_core::EpisodeError) -> Self {
        ServiceError::Simulator(e)
    }
}

impl From<esrp_render::RenderError> for ServiceError {
    fn from(e: esrp_render::RenderError) -> Self {
        ServiceError::Render(e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each typed error has its code and says what to change.
    fn check(error: ServiceError, code: Code, needle: &str) {
        let status = Status::from(error);
        assert_eq!(status.code(), code, "{status:?}");
        assert!(status.message().contains(needle), "{:?} does not contain {needle:?}", status.message());
    }

    #[test]
    fn client_values_in_messages_are_bounded() {
        let long = "é".repeat(20_000);
        for error in [
            ServiceError::UnknownEpisode(EpisodeId::from(long.as_str())),
            ServiceError::NotPrivileged(EpisodeId::from(long.as_str())),
            ServiceError::EpisodeOver { at: "step".into(), episode: EpisodeId::from(long.as_str()), steps: 1 },
            ServiceError::DuplicateStep { at: "steps[1]".into(), episode: EpisodeId::from(long.as_str()) },
            ServiceError::UnknownScene(long.clone()),
        ] {
            let message = error.to_string();
            assert!(message.len() < 512, "{message}");
            assert!(message.contains("(20000 characters)"), "{message}");
        }
    }

    #[test]
    fn typed_errors_map_to_their_codes_and_messages() {
        check(ServiceError::TooManyEpisodes { max: 7 }, Code::ResourceExhausted, "maximum of 7 live episodes");
        check(
            ServiceError::BatchTooLarge { steps: 9, max: 8 },
            Code::ResourceExhausted,
            "9 steps and resets exceeds the limit of 8",
        );
        check(
            ServiceError::StepAnswerTooLarge { bytes: 2_500_000, max: 1_000_000 },
            Code::ResourceExhausted,
            "about 2.5 MB, over the 1.0 MB",
        );
        check(
            ServiceError::CreateAnswerTooLarge { bytes: 2_500_000, max: 1_000_000 },
            Code::ResourceExhausted,
            "this create would take about 2.5 MB",
        );
        check(
            ServiceError::BatchAnswerTooLarge { steps: 3, bytes: 2_500_000, max: 1_000_000 },
            Code::ResourceExhausted,
            "these 3 steps would take about 2.5 MB",
        );
        let episode = EpisodeId::from("e1");
        check(
            ServiceError::EpisodeOver { at: "steps[2]".into(), episode: episode.clone(), steps: 4 },
            Code::FailedPrecondition,
            "steps[2]: episode e1 has ended after 4 steps",
        );
        check(ServiceError::UnknownEpisode(episode.clone()), Code::NotFound, "no episode \"e1\"");
        check(ServiceError::NotPrivileged(episode.clone()), Code::PermissionDenied, "episode e1 was not created");
        check(
            ServiceError::DuplicateStep { at: "steps[1]".into(), episode },
            Code::InvalidArgument,
            "e1 appears twice",
        );
        check(ServiceError::InvalidResolution { resolution: 9, max: 512 }, Code::InvalidArgument, "16 to 512");
        check(ServiceError::EmptySplit(Split::Train), Code::InvalidArgument, "no train scenes");
        check(
            ServiceError::Quota {
                caller: "token \"a\" (role agent)".into(),
                what: "live episodes",
                quota: "max_episodes",
                limit: 2,
            },
            Code::ResourceExhausted,
            "token \"a\" (role agent) already has 2 live episodes open, its quota (max_episodes",
        );
        check(
            ServiceError::from(AlreadyPlayed {
                scene: "challenge/00001".into(),
                caller: "token \"a\"".into(),
                when: "ended x".into(),
            }),
            Code::FailedPrecondition,
            "challenge scene \"challenge/00001\" was already played by token \"a\" (ended x)",
        );
        check(
            ServiceError::NotYours { episode: EpisodeId::from("e9"), caller: "token \"b\" (role agent)".into() },
            Code::PermissionDenied,
            "episode e9 belongs to another token: token \"b\" (role agent) may use only",
        );
        check(
            ServiceError::PlanDeadline { budget_ms: 40 },
            Code::DeadlineExceeded,
            "the planner found no plan within its budget of 40 ms",
        );
        check(
            ServiceError::PlannersBusy { budget_ms: 40, threads: 2 },
            Code::DeadlineExceeded,
            "no planner thread came free within the budget of 40 ms: all 2 (--planner-threads) were planning",
        );
        let unknown = esrp_core::Action::from_code(6).unwrap_err();
        check(
            ServiceError::InvalidAction { at: "step".into(), error: unknown },
            Code::InvalidArgument,
            "step.action: ",
        );
    }
}
