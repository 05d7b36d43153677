//! The agent's heading as an index of 16 (SPEC §1): exact, exactly reversible turns and an exact
//! table of sines and cosines, so no decision ever depends on a platform's `sin`.

use serde::{Deserialize, Serialize};

/// Number of distinct headings: one turn is `2π / 16 = 22.5°`.
pub const HEADING_COUNT: u8 = 16;

/// One turn, in radians (`π / 8`).
pub const TURN_ANGLE: f64 = std::f64::consts::FRAC_PI_8;

const C1: f64 = 0.923_879_532_511_286_7; // cos 22.5°
const C2: f64 = std::f64::consts::FRAC_1_SQRT_2; // cos 45°
const C3: f64 = 0.382_683_432_365_089_8; // cos 67.5°

/// `cos(k · 22.5°)` for `k` in `0..16`, written out so that every machine uses the same bits.
const COS: [f64; 16] = [1.0, C1, C2, C3, 0.0, -C3, -C2, -C1, -1.0, -C1, -C2, -C3, 0.0, C3, C2, C1];
/// `sin(k · 22.5°)` for `k` in `0..16`.
const SIN: [f64; 16] = [0.0, C3, C2, C1, 1.0, C1, C2, C3, 0.0, -C3, -C2, -C1, -1.0, -C1, -C2, -C3];

/// A heading index `k`, with yaw `θ = k · 22.5°`. Forward is `(cos θ, 0, −sin θ)`; `turn_left`
/// adds one (counter-clockwise seen from above).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Default, Serialize, Deserialize)]
#[serde(try_from = "u8", into = "u8")]
pub struct Heading(u8);

/// A heading index outside `0..16`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("heading index {0} is out of range: use an integer in 0..16 (yaw = index × 22.5°)")]
pub struct HeadingOutOfRange(pub u8);

impl Heading {
    /// The heading of index `k`, if `k < 16`.
    pub const fn new(k: u8) -> Result<Self, HeadingOutOfRange> {
        if k < HEADING_COUNT { Ok(Self(k)) } else { Err(HeadingOutOfRange(k)) }
    }

    /// The heading of index `k mod 16` (any integer, negative included).
    pub const fn wrapping(k: i64) -> Self {
        Self(k.rem_euclid(HEADING_COUNT as i64) as u8)
    }

    /// The index `k` in `0..16`.
    pub const fn index(self) -> u8 {
        self.0
    }

    /// Yaw in radians, in `[0, 2π)`.
    pub fn yaw(self) -> f64 {
        f64::from(self.0) * TURN_ANGLE
    }

    /// Exact `cos θ`.
    pub const fn cos(self) -> f64 {
        COS[self.0 as usize]
    }

    /// Exact `sin θ`.
    pub const fn sin(self) -> f64 {
        SIN[self.0 as usize]
    }

    /// The heading after one `turn_left` (+22.5°).
    pub const fn left(self) -> Self {
        Self((self.0 + 1) % HEADING_COUNT)
    }

    /// The heading after one `turn_right` (−22.5°).
    pub const fn right(self) -> Self {
        Self((self.0 + HEADING_COUNT - 1) % HEADING_COUNT)
    }

    /// The number of left turns that take `from` to `self`, in `0..16`.
    pub const fn turns_from(self, from: Heading) -> u8 {
        (self.0 + HEADING_COUNT - from.0) % HEADING_COUNT
    }
}

impl TryFrom<u8> for Heading {
    type Error = HeadingOutOfRange;
    fn try_from(k: u8) -> Result<Self, Self::Error> {
        Self::new(k)
    }
}

impl From<Heading> for u8 {
    fn from(h: Heading) -> u8 {
        h.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_matches_the_trigonometric_functions() {
        for k in 0..HEADING_COUNT {
            let h = Heading::new(k).unwrap();
            assert!((h.cos() - h.yaw().cos()).abs() < 1e-15, "cos at {k}");
            assert!((h.sin() - h.yaw().sin()).abs() < 1e-15, "sin at {k}");
            assert!((h.cos() * h.cos() + h.sin() * h.sin() - 1.0).abs() < 1e-15);
        }
    }

    #[test]
    fn turns_are_exactly_reversible_and_wrap() {
        let h = Heading::new(0).unwrap();
        assert_eq!(h.right().index(), 15);
        assert_eq!(h.right().left(), h);
        assert_eq!(Heading::new(15).unwrap().left().index(), 0);
        assert_eq!(Heading::wrapping(-1).index(), 15);
        assert_eq!(Heading::new(3).unwrap().turns_from(Heading::new(14).unwrap()), 5);
        assert!(Heading::new(16).is_err());
    }
}
