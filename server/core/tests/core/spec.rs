//! SPEC.md's numbers and edge cases, rule by rule, each at its boundary: a test here fails when
//! a number drifts (a margin of 0.015 m, a reach of 1.04 m, a threshold of 0.25) or an edge case
//! changes meaning, where `rules.rs` checks each rule's ordinary behaviour.

use esrp_core::world::{
    CAMERA_HEIGHT, CAMERA_HORIZONTAL_FOV, CAMERA_PITCH, MAX_MOVABLE_OBJECTS, MOVE_DISTANCE, ROBOT_HEIGHT, ROBOT_RADIUS,
};
use esrp_core::{
    Action, CompiledScene, Difficulty, Episode, EpisodeConfig, EpisodeError, EpisodeStatus, HEADING_COUNT, Obstacle,
    RewardWeights, Rules, Stage, TURN_ANGLE, footprint_iou,
};

use super::fixtures::{SceneBuilder, box_part, cylinder_part, pose, small_box};

fn step(episode: &mut Episode, action: Action) -> esrp_core::StepOutcome {
    episode.step(action).expect("episode is running")
}

#[test]
fn the_defaults_are_the_spec_numbers() {
    // §3: 0.25 m moves, 22.5° turns on 16 headings, six action codes in this order.
    assert_eq!(MOVE_DISTANCE, 0.25);
    assert_eq!(HEADING_COUNT, 16);
    assert!((TURN_ANGLE.to_degrees() - 22.5).abs() < 1e-12);
    let names: Vec<_> = Action::ALL.iter().map(|a| (a.code(), a.name())).collect();
    assert_eq!(
        names,
        [(0, "move_forward"), (1, "move_backward"), (2, "turn_left"), (3, "turn_right"), (4, "fetch"), (5, "release")]
    );
    // §3 and §5: margin 0.01 m, reach 1.0 m, placement IoU > 0.3.
    let rules = Rules::default();
    assert_eq!((rules.collision_margin, rules.fetch_reach, rules.placement_iou), (0.01, 1.0, 0.3));
    // §2: the robot and its camera.
    assert_eq!((ROBOT_RADIUS, ROBOT_HEIGHT, CAMERA_HEIGHT), (0.30, 1.10, 1.25));
    assert!((CAMERA_PITCH.to_degrees() - 20.0).abs() < 1e-12);
    assert!((CAMERA_HORIZONTAL_FOV.to_degrees() - 90.0).abs() < 1e-12);
    // §6: +10 success, ±1 place / unplace, potential factor 1, +0.01 holding, living 0.
    let w = RewardWeights::default();
    assert_eq!((w.success, w.place, w.unplace, w.potential, w.holding, w.living), (10.0, 1.0, -1.0, 1.0, 0.01, 0.0));
    // §5 and §7: at most 6 objects; Easy 1, Medium 2–3, Hard 4–6.
    assert_eq!(MAX_MOVABLE_OBJECTS, 6);
    let levels: Vec<_> = (0..=7).map(Difficulty::for_object_count).collect();
    use Difficulty::{Easy, Hard, Medium};
    assert_eq!(levels, [None, Some(Easy), Some(Medium), Some(Medium), Some(Hard), Some(Hard), Some(Hard), None]);
}

#[test]
fn the_margin_is_one_centimetre_for_the_robot_and_the_held_object_in_translation() {
    // Facing the wall at x = 0: after the move the robot's edge is 0.009 m from it (rejected)
    // or 0.011 m (accepted).
    let robot = |x: f64| {
        SceneBuilder::room(5.0, 5.0)
            .agent(x, 2.5, 8)
            .movable("box", small_box(), pose(4.6, 4.6, 0.0), pose(4.6, 0.4, 0.0))
            .episode()
    };
    assert_eq!(step(&mut robot(0.559), Action::MoveForward).collided_with, Some(Obstacle::Wall(3)));
    assert!(step(&mut robot(0.561), Action::MoveForward).accepted);

    // Carrying a 0.4 m box towards the wall at x = 5: after the move its far face is 0.009 m
    // from the wall (rejected) or 0.011 m (accepted); the robot stays far from everything.
    let carrying = |box_x: f64| {
        let mut e = SceneBuilder::room(5.0, 5.0)
            .agent(box_x - 1.0, 2.5, 0)
            .movable("box", small_box(), pose(box_x, 2.5, 0.0), pose(1.0, 1.0, 0.0))
            .episode();
        assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
        step(&mut e, Action::MoveForward)
    };
    assert_eq!(carrying(5.0 - 0.45 - 0.009).collided_with, Some(Obstacle::Wall(1)));
    assert!(carrying(5.0 - 0.45 - 0.011).accepted);
}

#[test]
fn the_margin_holds_along_a_turn_too() {
    // The agent at (3, 3) facing +x carries a 0.2 m square post whose far corners are
    // r = hypot(1.1, 0.1) from the turning axis. A pole of radius 0.05 stands at 11.25° to the
    // left, its surface `gap` beyond r: the held post passes it at exactly `gap` half-way through
    // a left turn, and is farther from it at both ends.
    let turn = |gap: f64| {
        let angle = std::f64::consts::PI / 16.0;
        let d = 1.1f64.hypot(0.1) + 0.05 + gap;
        let scene = SceneBuilder::room(6.0, 6.0)
            .agent(3.0, 3.0, 0)
            .fixed("pole", vec![cylinder_part(0.05, 1.0)], 3.0 + d * angle.cos(), 3.0 - d * angle.sin(), 0.0)
            .movable("post", vec![box_part(0.1, 0.1, 0.6)], pose(4.0, 3.0, 0.0), pose(1.0, 1.0, 0.0))
            .compile();
        let mut e = Episode::new(scene, EpisodeConfig::default()).unwrap();
        assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
        step(&mut e, Action::TurnLeft)
    };
    assert_eq!(turn(0.009).collided_with, Some(Obstacle::Fixed(0)));
    assert!(turn(0.011).accepted);
}

#[test]
fn a_rejected_motion_names_the_obstacle_it_meets_first() {
    // A thin movable board stands 0.08 m in front of the robot and 0.08 m short of the wall: the
    // move would sweep into both, and the board comes first.
    let mut e = SceneBuilder::room(5.0, 5.0)
        .agent(4.5, 2.5, 0)
        .movable("board", vec![box_part(0.02, 0.4, 0.5)], pose(4.9, 2.5, 0.0), pose(1.0, 1.0, 0.0))
        .episode();
    assert_eq!(step(&mut e, Action::MoveForward).collided_with, Some(Obstacle::Movable(0)));
}

#[test]
fn fetch_needs_neither_facing_nor_a_clear_line_of_sight() {
    // SPEC §3 asks only for the footprint distance: an object right behind the agent is taken.
    let mut e = SceneBuilder::room(6.0, 6.0)
        .agent(3.0, 3.0, 0)
        .movable("behind", small_box(), pose(2.25, 3.0, 0.0), pose(1.0, 5.0, 0.0))
        .episode();
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));

    // And one hidden behind a fixed cabinet as tall as the camera, still within 1.0 m.
    let mut e = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 3.0, 0)
        .fixed("cabinet", vec![box_part(0.05, 0.6, 1.5)], 2.45, 3.0, 0.0)
        .movable("hidden", small_box(), pose(2.85, 3.0, 0.0), pose(1.0, 5.0, 0.0))
        .episode();
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
}

#[test]
fn fetch_ties_go_to_the_smallest_absolute_bearing_from_the_forward_vector() {
    // The agent faces −z (heading 4). Every box is 0.75 m from it (footprint 0.55 m away).
    let scene = |objects: &[(f64, f64)]| {
        let mut b = SceneBuilder::room(6.0, 6.0).agent(3.0, 3.0, 4);
        for (i, &(x, z)) in objects.iter().enumerate() {
            b = b.movable(&format!("o{i}"), small_box(), pose(x, z, 0.0), pose(0.5 + i as f64, 5.5, 0.0));
        }
        b.episode()
    };
    // The bearing is measured from the forward vector (−z), not from the world's +x.
    assert_eq!(scene(&[(3.75, 3.0), (3.0, 2.25)]).fetch_candidate(), Some(1));
    // Right (index 0) and left (index 1) have the same absolute bearing: the smaller index wins,
    // whatever the bearing's sign.
    assert_eq!(scene(&[(3.75, 3.0), (2.25, 3.0)]).fetch_candidate(), Some(0));
    assert_eq!(scene(&[(2.25, 3.0), (3.75, 3.0)]).fetch_candidate(), Some(0));
    // Behind (180°) loses to the side (90°).
    assert_eq!(scene(&[(3.0, 3.75), (2.25, 3.0)]).fetch_candidate(), Some(1));
}

/// A 0.4 m box fetched at x = 3 and carried one step to x = 3.25, with its target `offset` further
/// along x, under `rules`: the release's outcome and the IoU it was judged by.
fn release_short_of_target(offset: f64, rules: Rules) -> (esrp_core::StepOutcome, f64) {
    let scene = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .movable("box", small_box(), pose(3.0, 2.0, 0.0), pose(3.25 + offset, 2.0, 0.0))
        .build();
    let scene = std::sync::Arc::new(CompiledScene::new(scene, rules).unwrap());
    let mut e = Episode::new(scene.clone(), EpisodeConfig::default()).unwrap();
    step(&mut e, Action::Fetch);
    assert!(step(&mut e, Action::MoveForward).accepted);
    let o = step(&mut e, Action::Release);
    let target = scene.scene().movable_objects[0].target;
    let iou = footprint_iou(&scene.movable_footprint(0, &e.object_poses()[0]), &scene.movable_footprint(0, &target));
    assert_eq!(e.placed()[0], o.placed_count == 1);
    (o, iou)
}

#[test]
fn placed_means_iou_strictly_above_0_3() {
    // IoU (0.4 − d) / (0.4 + d): 0.3115 at d = 0.21 (placed, and so success), 0.2903 at d = 0.22.
    let (o, iou) = release_short_of_target(0.21, Rules::default());
    assert!(iou > 0.3 && iou < 0.32, "{iou}");
    assert!(o.terminated && o.placed_count == 1);
    let (o, iou) = release_short_of_target(0.22, Rules::default());
    assert!(iou < 0.3 && iou > 0.28, "{iou}");
    assert!(!o.terminated && o.placed_count == 0 && o.reward.placement == 0.0);

    // At a threshold equal to the IoU bit for bit the object is not placed; one ulp lower it is.
    let (_, iou) = release_short_of_target(0.2, Rules::default());
    let (o, _) = release_short_of_target(0.2, Rules { placement_iou: iou, ..Rules::default() });
    assert_eq!(o.placed_count, 0);
    let (o, _) = release_short_of_target(0.2, Rules { placement_iou: iou.next_down(), ..Rules::default() });
    assert_eq!(o.placed_count, 1);
}

#[test]
fn success_on_the_last_step_terminates_rather_than_truncates() {
    let mut e = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .horizon(4)
        .movable("box", small_box(), pose(3.0, 2.0, 0.0), pose(3.5, 2.0, 0.0))
        .episode();
    for action in [Action::Fetch, Action::MoveForward, Action::MoveForward] {
        assert!(!step(&mut e, action).truncated);
    }
    let o = step(&mut e, Action::Release);
    assert_eq!((o.step_index, o.terminated, o.truncated, o.reward.success), (4, true, false, 10.0));
    assert_eq!(e.status(), EpisodeStatus::Succeeded);
    assert_eq!(e.metrics().stage, Stage::Succeeded);
    assert!(matches!(e.step(Action::Fetch), Err(EpisodeError::Finished { reason: "success", steps: 4 })));
}

#[test]
fn a_horizon_override_of_zero_is_refused_and_others_replace_the_scenes() {
    let scene = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .horizon(7)
        .movable("box", small_box(), pose(3.0, 2.0, 0.0), pose(3.5, 2.0, 0.0))
        .compile();
    let zero = EpisodeConfig { horizon: Some(0), ..Default::default() };
    assert!(matches!(Episode::new(scene.clone(), zero), Err(EpisodeError::InvalidConfig { .. })));
    assert_eq!(Episode::new(scene.clone(), EpisodeConfig::default()).unwrap().horizon(), 7);
    let mut e = Episode::new(scene, EpisodeConfig { horizon: Some(1), ..Default::default() }).unwrap();
    assert!(step(&mut e, Action::TurnLeft).truncated);
    assert_eq!(e.status(), EpisodeStatus::Truncated);
}

#[test]
fn stage_one_and_two_depend_on_ever_being_in_reach_not_on_trying_to_fetch() {
    // The box's footprint is 1.2 m ahead: out of reach, and a fetch there fails.
    let scene = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 3.0, 0)
        .horizon(3)
        .movable("box", small_box(), pose(3.4, 3.0, 0.0), pose(1.0, 5.0, 0.0))
        .compile();
    let play = |actions: &[Action]| {
        let mut e = Episode::new(scene.clone(), EpisodeConfig::default()).unwrap();
        for &a in actions {
            step(&mut e, a);
        }
        assert!(e.is_over());
        e.metrics().stage
    };
    use Action::{Fetch, MoveBackward, MoveForward, TurnLeft};
    assert_eq!(play(&[Fetch, Fetch, TurnLeft]), Stage::NeverReached);
    // One step forward brings it to 0.95 m: reached, even after stepping back out of reach.
    assert_eq!(play(&[MoveForward, MoveBackward, Fetch]), Stage::NeverFetched);
    assert_eq!(play(&[MoveForward, Fetch, MoveBackward]), Stage::Fetched);
}

#[test]
fn objects_placed_at_the_start_count_in_osr_and_rdr_is_end_over_start() {
    // Object 0 starts placed, object 1 does not; the agent only turns until the horizon.
    let mut e = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .horizon(2)
        .movable("placed", small_box(), pose(4.0, 4.0, 0.0), pose(4.05, 4.0, 0.0))
        .movable("away", small_box(), pose(5.0, 1.0, 0.0), pose(1.0, 5.0, 0.0))
        .episode();
    step(&mut e, Action::TurnLeft);
    assert!(step(&mut e, Action::TurnLeft).truncated);
    let m = e.metrics();
    assert_eq!((m.success, m.placed, m.movable_objects, m.object_success_rate), (false, 1, 2, 0.5));
    assert!((m.distance_start - (0.05 + 4.0f64.hypot(4.0))).abs() < 1e-12);
    assert_eq!(m.distance_now, m.distance_start);
    assert_eq!(m.remaining_distance_ratio, 1.0);
}

#[test]
fn rdr_measures_footprint_centres_and_is_finite_when_the_start_distance_is_zero() {
    // The box's model is off-centre: its footprint centre is 0.3 m from its pose's origin along
    // local x. Turned half a circle at the same position, the centres are 0.6 m apart.
    let offset_box = vec![esrp_core::Part::Box { half_extents: [0.2, 0.25, 0.2], offset: [0.3, 0.25, 0.0], yaw: 0.0 }];
    let e = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .movable("box", offset_box, pose(4.0, 4.0, 0.0), pose(4.0, 4.0, std::f64::consts::PI))
        .episode();
    assert!((e.metrics().distance_start - 0.6).abs() < 1e-12);

    // A 0.8 × 0.2 bar turned 90° about its own centre: IoU 0.04 / 0.28, not placed, yet its
    // footprint centre is on the target's, so D_start = 0. SPEC §5 leaves 0 / 0 open; the
    // metrics stay finite (RDR 0) so that means over episodes are numbers.
    let e = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .movable("bar", vec![box_part(0.4, 0.1, 0.5)], pose(4.0, 4.0, 0.0), pose(4.0, 4.0, std::f64::consts::FRAC_PI_2))
        .episode();
    let m = e.metrics();
    assert_eq!((m.placed, m.distance_start, m.distance_now), (0, 0.0, 0.0));
    assert_eq!(m.remaining_distance_ratio, 0.0);
}

#[test]
fn a_rejected_motion_pays_no_potential_but_holding_still_pays_and_moving_away_costs() {
    // Carrying the box towards the wall at x = 5, away from its target at x = 1.
    let mut e = SceneBuilder::room(5.0, 5.0)
        .agent(3.0, 2.5, 0)
        .movable("box", small_box(), pose(4.0, 2.5, 0.0), pose(1.0, 2.5, 0.0))
        .episode();
    step(&mut e, Action::Fetch);
    let o = step(&mut e, Action::MoveForward);
    assert!(o.accepted);
    assert!((o.reward.potential + 0.25).abs() < 1e-12, "{:?}", o.reward);
    for _ in 0..2 {
        step(&mut e, Action::MoveForward);
    }
    let o = step(&mut e, Action::MoveForward);
    assert!(o.collided());
    assert_eq!((o.reward.potential, o.reward.holding, o.reward.total), (0.0, 0.01, 0.01));
}

#[test]
fn an_ended_episode_refuses_steps_keeps_its_metrics_and_resets_to_a_running_start() {
    let mut e = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .horizon(2)
        .movable("box", small_box(), pose(3.0, 2.0, 0.0), pose(3.5, 2.0, 0.0))
        .episode();
    let fresh = e.clone();
    step(&mut e, Action::Fetch);
    assert!(step(&mut e, Action::MoveForward).truncated);
    let ended = e.metrics();
    for action in Action::ALL {
        assert!(matches!(e.step(action), Err(EpisodeError::Finished { reason: "horizon reached", steps: 2 })));
    }
    assert_eq!(e.metrics(), ended);
    assert_eq!((ended.steps, ended.stage), (2, Stage::Fetched));
    e.reset();
    assert!(e.same_state(&fresh));
    assert_eq!((e.status(), e.steps(), e.held()), (EpisodeStatus::Running, 0, None));
    assert_eq!(e.metrics(), fresh.metrics());
    assert_eq!(step(&mut e, Action::Fetch).step_index, 1);
}
