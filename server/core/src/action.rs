//! The six discrete actions and their integer codes (SPEC §3), the same in the proto, in Python
//! and in Rust.

use serde::{Deserialize, Serialize};

/// One of the six ESRP actions. The discriminant is the action's code everywhere.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "u8", into = "u8")]
#[repr(u8)]
pub enum Action {
    /// Code 0: translate 0.25 m along the forward vector.
    MoveForward = 0,
    /// Code 1: translate 0.25 m against the forward vector.
    MoveBackward = 1,
    /// Code 2: rotate +22.5° in place.
    TurnLeft = 2,
    /// Code 3: rotate −22.5° in place.
    TurnRight = 3,
    /// Code 4: attach the nearest movable object within reach.
    Fetch = 4,
    /// Code 5: detach the held object where it is.
    Release = 5,
}

/// An action code outside `0..=5`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown action code {0}: use 0 move_forward, 1 move_backward, 2 turn_left, 3 turn_right, 4 fetch, 5 release")]
pub struct UnknownAction(pub i64);

impl Action {
    /// All actions in code order.
    pub const ALL: [Action; 6] = [
        Action::MoveForward,
        Action::MoveBackward,
        Action::TurnLeft,
        Action::TurnRight,
        Action::Fetch,
        Action::Release,
    ];

    /// The action's integer code.
    pub const fn code(self) -> u8 {
        self as u8
    }

    /// The action of a code, if the code is in `0..=5`.
    pub fn from_code(code: i64) -> Result<Action, UnknownAction> {
        match code {
            0 => Ok(Action::MoveForward),
            1 => Ok(Action::MoveBackward),
            2 => Ok(Action::TurnLeft),
            3 => Ok(Action::TurnRight),
            4 => Ok(Action::Fetch),
            5 => Ok(Action::Release),
            other => Err(UnknownAction(other)),
        }
    }

    /// The snake-case name used in SPEC §3 (`move_forward`, ...).
    pub const fn name(self) -> &'static str {
        match self {
            Action::MoveForward => "move_forward",
            Action::MoveBackward => "move_backward",
            Action::TurnLeft => "turn_left",
            Action::TurnRight => "turn_right",
            Action::Fetch => "fetch",
            Action::Release => "release",
        }
    }

    /// The action that undoes this one: forward ↔ backward, left ↔ right, fetch ↔ release
    /// (SPEC §7, used to reverse a generation run into an expert trajectory).
    pub const fn inverse(self) -> Action {
        match self {
            Action::MoveForward => Action::MoveBackward,
            Action::MoveBackward => Action::MoveForward,
            Action::TurnLeft => Action::TurnRight,
            Action::TurnRight => Action::TurnLeft,
            Action::Fetch => Action::Release,
            Action::Release => Action::Fetch,
        }
    }

    /// Whether the action moves the agent (and so is collision-checked).
    pub const fn is_motion(self) -> bool {
        matches!(self, Action::MoveForward | Action::MoveBackward | Action::TurnLeft | Action::TurnRight)
    }
}

impl TryFrom<u8> for Action {
    type Error = UnknownAction;
    fn try_from(code: u8) -> Result<Self, Self::Error> {
        Action::from_code(i64::from(code))
    }
}

impl From<Action> for u8 {
    fn from(a: Action) -> u8 {
        a.code()
    }
}

/// Reverses a generation run into the trajectory that undoes it: the actions in reverse order,
/// each replaced by its inverse (SPEC §7).
pub fn reverse_trajectory(actions: &[Action]) -> Vec<Action> {
    actions.iter().rev().map(|a| a.inverse()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_round_trip_and_bad_codes_say_what_is_allowed() {
        for a in Action::ALL {
            assert_eq!(Action::from_code(i64::from(a.code())), Ok(a));
            assert_eq!(a.inverse().inverse(), a);
        }
        let err = Action::from_code(6).unwrap_err();
        assert!(err.to_string().contains("5 release"));
        assert!(Action::from_code(-1).is_err());
        assert_eq!(serde_json::to_string(&Action::Fetch).unwrap(), "4");
        assert!(serde_json::from_str::<Action>("9").is_err());
    }

    #[test]
    fn reversing_inverts_and_reorders() {
        use Action::*;
        assert_eq!(
            reverse_trajectory(&[Fetch, MoveForward, TurnLeft, Release]),
            vec![Fetch, TurnRight, MoveBackward, Release]
        );
    }
}
