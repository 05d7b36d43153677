//! Property: from random benchmark scenes advanced by random actions (so the agent may hold an
//! object, objects may have moved or been placed), any plan returned replays to success with
//! every action accepted, within the horizon.

use esrp_core::{Action, Difficulty, Split};
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED};
use esrp_planner::{PlanFailure, PlanOptions, plan};
use proptest::prelude::*;

use crate::fixtures::{assert_replays_to_success, bench_episode};

/// The easy and medium test scenes among the first 300 (quick to generate in a debug build).
fn small_scenes() -> Vec<usize> {
    let bench = Benchmark::new(BenchVersion::V1, DEFAULT_SEED);
    (0..300)
        .filter(|&i| bench.split(i) == Split::Test)
        .filter(|&i| Difficulty::for_object_count(bench.object_count(i)) != Some(Difficulty::Hard))
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 16, ..ProptestConfig::default() })]

    #[test]
    fn plans_from_random_states_replay_to_success(
        pick in any::<prop::sample::Index>(),
        prefix in prop::collection::vec(0u8..6, 0..40),
    ) {
        let scenes = small_scenes();
        let index = scenes[pick.index(scenes.len())];
        let mut episode = bench_episode(index);
        // The expert first, partly, so that objects get fetched and moved; then random actions.
        let expert = episode.compiled().scene().expert_trajectory.clone();
        let from_expert = prefix.len().min(expert.len()) / 2;
        let actions = expert.iter().copied().take(from_expert)
            .chain(prefix.iter().filter_map(|&c| Action::from_code(i64::from(c)).ok()));
        for action in actions {
            if episode.is_over() {
                break;
            }
            episode.step(action).expect("a running episode");
        }
        match plan(&episode, &PlanOptions::default()) {
            Ok(found) => assert_replays_to_success(&episode, &found.actions),
            Err(error) => {
                prop_assert!(
                    !matches!(error.reason, PlanFailure::ReplayFailed { .. } | PlanFailure::InvalidOptions { .. }),
                    "scene {index}: {error:?}"
                );
                prop_assert!(episode.is_over() || !matches!(error.reason, PlanFailure::EpisodeOver));
            }
        }
    }
}
