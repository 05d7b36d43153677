//! esrp-bench-v2 starts: the agent begins away from every object, so each plan begins with an
//! approach (`approach` before the fetch-and-carry search).

use esrp_core::{Action, CompiledScene, Episode, EpisodeConfig};
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED};
use esrp_planner::{PlanOptions, plan};

use crate::fixtures::assert_replays_to_success;

fn v2_episode(index: usize) -> Episode {
    let scene = Benchmark::new(BenchVersion::V2, DEFAULT_SEED).generate(index).expect("the scene generates").scene;
    Episode::new(CompiledScene::shared(scene).expect("a valid scene"), EpisodeConfig::default()).expect("a config")
}

/// Easy test scenes whose agent starts far from the object: planned, replayed to success, the
/// same plan twice. `00706` took the fetch-and-carry search alone 112,644 nodes from its start
/// (it flooded the room's approach states); approach first, it takes far fewer.
#[test]
fn plans_from_a_start_away_from_the_objects() {
    for (index, most_nodes) in [(706, 40_000), (3, 40_000)] {
        let episode = v2_episode(index);
        assert_eq!(episode.fetch_candidate(), None, "scene {index} starts out of reach");
        let found = plan(&episode, &PlanOptions::default()).unwrap_or_else(|e| panic!("scene {index}: {e}"));
        assert_replays_to_success(&episode, &found.actions);
        assert!(found.stats.nodes_expanded < most_nodes, "scene {index}: {:?}", found.stats);
        assert!(found.actions.iter().position(|&a| a == Action::Fetch).unwrap() > 0);
        let again = plan(&episode, &PlanOptions::default()).unwrap();
        assert_eq!(again.actions, found.actions, "scene {index}: not deterministic");
    }
}
