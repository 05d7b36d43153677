//! What each role may do: the episode layer's edge policy, asked before a call moves anything.
//!
//! - `agent`: ordinary episodes only: no privileged episodes, hence no GetPrivilegedState or
//!   PlanActions (the scene's JSON and expert trajectory travel only in the privileged state).
//! - `trainer`: also privileged episodes and the planner, never on a hidden scene.
//! - `admin`: everything, other tokens' episodes included, but no token ever gets a hidden
//!   (challenge or minival) scene's privileged state: such episodes cannot be privileged.
//!
//! Who may name which episode (its creator, or an admin) is the registry's check.

use esrp_core::Split;

use crate::config::{Config, Observations};
use crate::error::ServiceError;
use crate::quote::quoted;
use crate::types::{Caller, Role, SensorConfig};

/// May `caller` create (or reset into) an episode on a scene of `split` with `privileged`, and
/// a horizon of its own (`own_horizon`) rather than the scene's? Hidden scenes are played at
/// their own horizon by every token but an admin (a longer one would be an advantage).
pub(super) fn may_play(caller: &Caller, split: Split, privileged: bool, own_horizon: bool) -> Result<(), ServiceError> {
    if own_horizon && split.is_hidden() && !caller.is_admin() {
        return Err(ServiceError::Denied(format!(
            "{} may not set the horizon of an episode on a {} scene: such episodes play the scene's own horizon \
             (send horizon = 0)",
            caller.describe(),
            split.as_str()
        )));
    }
    if !privileged {
        return Ok(());
    }
    if caller.role == Role::Agent {
        return Err(ServiceError::Denied(format!(
            "{} may not create privileged episodes (privileged = true): the privileged state, the scene's JSON, \
             its expert trajectory and PlanActions are for trainer and admin tokens",
            caller.describe()
        )));
    }
    if split.is_hidden() {
        return Err(ServiceError::Denied(format!(
            "episodes on {} scenes cannot be privileged, for any token: no one reads their state, JSON, expert \
             trajectory or plan; create it with privileged = false",
            split.as_str()
        )));
    }
    Ok(())
}

/// Whether an episode on a scene of `split` serves `caller` the paper's observation only: the
/// ego and goal images at 128 px and the grasp flag. So do the hidden splits, to every token but
/// an admin, unless the organiser widened them (`--challenge-observations`,
/// `--minival-observations`): reward, reward terms, placed counts, collisions and metrics
/// before the end would tell the agent how far the layout is from its target.
pub(super) fn paper_only(caller: &Caller, split: Split, config: &Config) -> bool {
    split_is_paper_only(split, config) && !caller.is_admin()
}

/// Whether episodes on `split` serve tokens other than admins the paper's observation only.
pub(super) fn split_is_paper_only(split: Split, config: &Config) -> bool {
    let policy = match split {
        Split::Challenge => config.challenge_observations,
        Split::Minival => config.minival_observations,
        Split::Train | Split::Test => Observations::Full,
    };
    policy == Observations::Paper
}

/// Refuses what a paper-only episode (see [`paper_only`]) does not serve: an optional sensor,
/// another resolution, reward weights of the caller's own.
pub(super) fn may_observe(
    caller: &Caller,
    split: Split,
    sensors: &SensorConfig,
    own_reward: bool,
) -> Result<(), ServiceError> {
    let mut asked = Vec::new();
    if sensors.depth {
        asked.push("ego_depth".to_owned());
    }
    if sensors.segmentation {
        asked.push("ego_segmentation".to_owned());
    }
    if sensors.current_top_down {
        asked.push("current_top_down".to_owned());
    }
    if sensors.resolution != esrp_render::DEFAULT_RESOLUTION {
        asked.push(format!("resolution {}", sensors.resolution));
    }
    if own_reward {
        asked.push("reward weights".to_owned());
    }
    if asked.is_empty() {
        return Ok(());
    }
    Err(ServiceError::Denied(format!(
        "{} plays {} scenes with the paper's observation only: the ego and goal images at {} px and the grasp \
         flag, no reward, placed count, collision or metrics before the end; it may not ask for {} (create it \
         with the default sensors and no reward weights)",
        caller.describe(),
        split.as_str(),
        esrp_render::DEFAULT_RESOLUTION,
        asked.join(", ")
    )))
}

/// Refuses the metrics of a paper-only episode that has not ended.
pub(super) fn may_read_metrics(
    caller: &Caller,
    split: Split,
    paper_only: bool,
    ended: bool,
) -> Result<(), ServiceError> {
    if paper_only && !ended {
        return Err(ServiceError::Denied(format!(
            "{} reads the metrics of an episode on a {} scene only once it has ended: such episodes serve the \
             paper's observation only",
            caller.describe(),
            split.as_str()
        )));
    }
    Ok(())
}

/// May `caller` call `what` (GetPrivilegedState, PlanActions) at all?
pub(super) fn may_read_privileged(caller: &Caller, what: &str) -> Result<(), ServiceError> {
    if caller.role == Role::Agent {
        return Err(ServiceError::Denied(format!(
            "{} may not call {what}: it is for trainer and admin tokens, on privileged episodes",
            caller.describe()
        )));
    }
    Ok(())
}

/// Refuses an inline scene that claims a hidden split: only the server's own hidden scenes
/// are hidden.
pub(super) fn inline_split(split: Split) -> Result<(), ServiceError> {
    if split.is_hidden() {
        return Err(ServiceError::InvalidArgument(format!(
            "an inline scene cannot claim the split {}: use train or test",
            split.as_str()
        )));
    }
    Ok(())
}

/// The id namespaces (what comes before the `/`) of the server's own scenes, which no inline scene
/// may take: the built-in benchmarks' and the hidden splits'.
const RESERVED_NAMESPACES: [&str; 4] =
    [esrp_dataset::BENCH_V1, esrp_dataset::BENCH_V2, Split::Challenge.as_str(), Split::Minival.as_str()];

/// Refuses an inline scene whose id is one of the served scenes' (`served`) or lies in the
/// namespace of the server's own scenes: records, leaderboards and verification name a scene by
/// its id, so an inline scene must never pass for one of the server's.
pub(super) fn inline_id(id: &str, served: bool) -> Result<(), ServiceError> {
    let namespace = id.split_once('/').map(|(namespace, _)| namespace);
    let reserved = namespace.filter(|n| RESERVED_NAMESPACES.contains(n));
    if served || reserved.is_some() {
        let whose = reserved.map_or_else(String::new, |n| format!(" (`{n}/…` names the server's own scenes)"));
        return Err(ServiceError::InvalidArgument(format!(
            "an inline scene cannot take the id {}{whose}: records name the server's scenes by id; give it an id of its own",
            quoted(id)
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn caller(role: Role) -> Caller {
        Caller { name: "c".into(), role, max_episodes: None, max_streams: None }
    }

    #[test]
    fn each_role_gets_what_it_may() {
        let (agent, trainer, admin) = (caller(Role::Agent), caller(Role::Trainer), caller(Role::Admin));
        for split in Split::ALL {
            for c in [&agent, &trainer, &admin] {
                assert!(may_play(c, split, false, false).is_ok());
                assert_eq!(may_play(c, split, false, true).is_ok(), c.is_admin() || !split.is_hidden());
            }
            let denied = may_play(&agent, split, true, false).unwrap_err().to_string();
            assert!(denied.contains("token \"c\" (role agent) may not create privileged episodes"), "{denied}");
            assert_eq!(may_play(&trainer, split, true, false).is_ok(), !split.is_hidden());
            assert_eq!(may_play(&admin, split, true, false).is_ok(), !split.is_hidden());
        }
        assert!(
            may_read_privileged(&agent, "PlanActions").unwrap_err().to_string().contains("may not call PlanActions")
        );
        assert!(may_read_privileged(&trainer, "PlanActions").is_ok());
        assert!(inline_split(Split::Challenge).is_err() && inline_split(Split::Test).is_ok());
        for taken in ["esrp-bench-v2/00007", "esrp-bench-v1/00000", "challenge/00001", "minival/00000"] {
            let message = inline_id(taken, false).unwrap_err().to_string();
            assert!(message.contains("give it an id of its own"), "{message}");
        }
        assert!(inline_id("my-room", true).is_err(), "a served scene's id");
        assert!(inline_id("my-room", false).is_ok() && inline_id("example/bedroom-0", false).is_ok());
    }
}
