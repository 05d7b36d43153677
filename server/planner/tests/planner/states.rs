//! Planning from particular states: the start, holding an object, a placed object in the way,
//! an ended episode, and the limits (node budget, deadline, horizon, options).

use std::time::Instant;

use esrp_core::{Action, Episode, EpisodeConfig};
use esrp_planner::{PlanFailure, PlanOptions, plan};

use crate::fixtures::{
    assert_replays_to_success, bench_episode, bench_scene, compiled, episode_of, placed_blocker_scene,
};

/// A medium test scene (two objects) and an easy one.
const MEDIUM: usize = 50;
const EASY: usize = 7;

fn failure(episode: &Episode, options: &PlanOptions) -> PlanFailure {
    match plan(episode, options) {
        Ok(found) => panic!("expected a failure, got a plan of {} actions", found.actions.len()),
        Err(error) => error.reason,
    }
}

#[test]
fn plans_from_the_start_replay_to_success_and_are_deterministic() {
    for index in [EASY, MEDIUM] {
        let episode = bench_episode(index);
        let first = plan(&episode, &PlanOptions::default()).expect("a plan");
        assert_replays_to_success(&episode, &first.actions);
        assert!(first.stats.searches >= episode.object_poses().len() as u32);
        let second = plan(&episode, &PlanOptions::default()).expect("a plan");
        assert_eq!(first.actions, second.actions, "scene {index}: the same state gave two plans");
        assert_eq!(first.stats.nodes_expanded, second.stats.nodes_expanded);
    }
}

#[test]
fn starting_while_holding_an_object() {
    let scene = bench_scene(MEDIUM);
    let expert = scene.expert_trajectory.clone();
    let mut episode = episode_of(scene);
    // The expert starts next to the object it fetches first; take it and carry it a little.
    assert_eq!(expert.first(), Some(&Action::Fetch));
    for &action in expert.iter().take(3) {
        episode.step(action).expect("a running episode");
    }
    assert!(episode.held().is_some(), "the test needs an object in hand");
    let found = plan(&episode, &PlanOptions::default()).expect("a plan");
    assert_replays_to_success(&episode, &found.actions);
}

#[test]
fn a_placed_object_on_another_target_is_moved_out_of_the_way() {
    let episode = episode_of(placed_blocker_scene());
    assert_eq!(episode.placed(), &[true, false], "stool-a starts placed, stool-b not");
    let found = plan(&episode, &PlanOptions::default()).expect("a plan");
    assert_replays_to_success(&episode, &found.actions);
    // stool-a had to be fetched (taken off its target) before stool-b could be placed.
    let mut replay = episode.clone();
    let mut fetched = Vec::new();
    for &action in &found.actions {
        if let Ok(outcome) = replay.step(action)
            && let Some(object) = outcome.fetched
        {
            fetched.push(object);
        }
    }
    assert_eq!(fetched.first(), Some(&0), "stool-a must move first: fetched {fetched:?}");
    assert!(fetched.contains(&1));
}

#[test]
fn an_ended_episode_has_nothing_to_plan() {
    let scene = bench_scene(EASY);
    let expert = scene.expert_trajectory.clone();
    let mut succeeded = episode_of(scene.clone());
    for action in expert {
        succeeded.step(action).expect("a running episode");
    }
    assert!(succeeded.is_over());
    assert_eq!(failure(&succeeded, &PlanOptions::default()), PlanFailure::EpisodeOver);

    let config = EpisodeConfig { horizon: Some(2), ..EpisodeConfig::default() };
    let mut truncated = Episode::new(compiled(scene), config).expect("a valid configuration");
    truncated.step(Action::TurnLeft).expect("a running episode");
    truncated.step(Action::TurnLeft).expect("a running episode");
    assert!(truncated.is_over());
    assert_eq!(failure(&truncated, &PlanOptions::default()), PlanFailure::EpisodeOver);
}

#[test]
fn a_tiny_node_budget_is_exhausted() {
    let episode = bench_episode(MEDIUM);
    let options = PlanOptions { max_nodes: 3, ..PlanOptions::default() };
    match plan(&episode, &options) {
        Err(error) => {
            assert!(matches!(error.reason, PlanFailure::BudgetExhausted { nodes } if nodes <= 3), "{error:?}");
            assert!(error.stats.nodes_expanded <= 3);
        }
        Ok(found) => panic!("3 nodes planned {} actions", found.actions.len()),
    }
}

#[test]
fn a_past_deadline_is_exceeded() {
    let episode = bench_episode(MEDIUM);
    let options = PlanOptions { deadline: Some(Instant::now()), ..PlanOptions::default() };
    assert_eq!(failure(&episode, &options), PlanFailure::DeadlineExceeded);
}

#[test]
fn a_plan_the_deadline_cut_short_says_so_and_one_it_did_not_is_the_unhurried_plan() {
    let episode = bench_episode(MEDIUM);
    let unhurried = plan(&episode, &PlanOptions::default()).expect("a plan");
    assert!(!unhurried.stats.cut_short, "no deadline, nothing cut short");
    let full = unhurried.stats.elapsed.max(std::time::Duration::from_millis(1));
    // Deadlines across the whole call: some land while a search polishes a way it has found.
    let mut cut = 0;
    for attempt in 0..3u32 {
        let tries = 40 * (attempt + 1);
        for i in 1..=tries {
            let options = PlanOptions { deadline: Some(Instant::now() + full * i / tries), ..PlanOptions::default() };
            match plan(&episode, &options) {
                Ok(found) if found.stats.cut_short => {
                    cut += 1;
                    assert_replays_to_success(&episode, &found.actions);
                }
                Ok(found) => assert_eq!(found.actions, unhurried.actions, "deadline {i}/{tries}, not cut short"),
                Err(error) => assert_eq!(error.reason, PlanFailure::DeadlineExceeded, "deadline {i}/{tries}"),
            }
        }
        if cut > 0 {
            return;
        }
    }
    panic!("no deadline across {full:?} cut a search short");
}

#[test]
fn a_cancelled_plan_stops_and_says_so() {
    let episode = bench_episode(MEDIUM);
    let cancel = esrp_planner::CancelToken::new();
    let options = PlanOptions { cancel: Some(cancel.clone()), ..PlanOptions::default() };
    assert!(plan(&episode, &options).is_ok(), "a token not cancelled changes nothing");
    cancel.cancel();
    assert_eq!(failure(&episode, &options), PlanFailure::Cancelled);
}

#[test]
fn a_plan_longer_than_the_horizon_is_too_long() {
    let scene = bench_scene(MEDIUM);
    let config = EpisodeConfig { horizon: Some(6), ..EpisodeConfig::default() };
    let episode = Episode::new(compiled(scene), config).expect("a valid configuration");
    match failure(&episode, &PlanOptions::default()) {
        PlanFailure::TooLong { steps, steps_left } => {
            assert_eq!(steps_left, 6);
            assert!(steps > 6, "{steps}");
        }
        other => panic!("expected TooLong, got {other:?}"),
    }
}

#[test]
fn unusable_options_are_refused() {
    let episode = bench_episode(EASY);
    for options in [
        PlanOptions { heuristic_weight: 0.5, ..PlanOptions::default() },
        PlanOptions { heuristic_weight: f64::NAN, ..PlanOptions::default() },
        PlanOptions { duplicate_cell: -0.1, ..PlanOptions::default() },
        PlanOptions { iou_weight: f64::INFINITY, ..PlanOptions::default() },
    ] {
        assert!(matches!(failure(&episode, &options), PlanFailure::InvalidOptions { .. }), "{options:?}");
    }
}

#[test]
fn exact_duplicate_detection_also_plans() {
    let episode = bench_episode(EASY);
    let options = PlanOptions { duplicate_cell: 0.0, ..PlanOptions::default() };
    let found = plan(&episode, &options).expect("a plan");
    assert_replays_to_success(&episode, &found.actions);
}
