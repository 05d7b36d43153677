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

use crate::error::ServiceError;
use crate::quote::quoted;
use crate::types::{Caller, Role};

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
