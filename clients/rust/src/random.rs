//! [`RandomActions`]: uniform random actions from a seed, the same on every machine.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::types::Action;

/// Uniform random actions from a seed: ChaCha8 keyed by the seed (the key esrp-dataset's
/// `Dice::new(seed, 0, 0)` uses, so the tools' random agents act as they always have), and
/// rejection sampling without modulo bias. Portable: the same seed gives the same actions on
/// every machine.
#[derive(Clone, Debug)]
pub struct RandomActions(ChaCha8Rng);

impl RandomActions {
    /// The actions of `seed`.
    pub fn new(seed: u64) -> Self {
        let mut key = [0u8; 32];
        key[..8].copy_from_slice(&seed.to_le_bytes());
        key[24..].copy_from_slice(b"esrp-v1\0");
        Self(ChaCha8Rng::from_seed(key))
    }

    /// The next action.
    pub fn next_action(&mut self) -> Action {
        const N: u64 = Action::ALL.len() as u64;
        let zone = u64::MAX - u64::MAX % N;
        loop {
            let v = self.0.next_u64();
            if v < zone {
                return Action::ALL[(v % N) as usize];
            }
        }
    }
}

impl Iterator for RandomActions {
    type Item = Action;

    fn next(&mut self) -> Option<Action> {
        Some(self.next_action())
    }
}
