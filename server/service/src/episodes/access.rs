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
    }
}
