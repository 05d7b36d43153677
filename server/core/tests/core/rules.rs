//! One test per rule of SPEC §3–6, on small hand-made scenes.

use esrp_core::collision::object_pose;
use esrp_core::parry3d::math::Pose;
use esrp_core::parry3d::query;
use esrp_core::{
    Action, CompiledScene, Episode, EpisodeConfig, EpisodeError, NoOpReason, Obstacle, Opening, OpeningKind, Scene,
    Stage,
};

use super::fixtures::{SceneBuilder, box_part, cylinder_part, pose, small_box};

/// A 5 × 5 room with the agent at `(x, z)` facing `heading` and one small box far away in a
/// corner, so that nothing is in reach.
fn open_room(x: f64, z: f64, heading: u8) -> Episode {
    SceneBuilder::room(5.0, 5.0)
        .agent(x, z, heading)
        .movable("box", small_box(), pose(4.6, 4.6, 0.0), pose(4.6, 0.4, 0.0))
        .episode()
}

fn step(episode: &mut Episode, action: Action) -> esrp_core::StepOutcome {
    episode.step(action).expect("episode is running")
}

#[test]
fn move_forward_and_backward_translate_along_the_heading() {
    let mut e = open_room(2.0, 2.0, 0);
    let o = step(&mut e, Action::MoveForward);
    assert!(o.accepted && !o.collided());
    assert_eq!(e.agent_pose().position.x, 2.25);
    assert_eq!(e.agent_pose().position.z, 2.0);
    step(&mut e, Action::MoveBackward);
    step(&mut e, Action::MoveBackward);
    assert_eq!(e.agent_pose().position.x, 1.75);

    // Heading 4 is 90° to the left of +x: forward is −z (SPEC §1).
    let mut e = open_room(2.0, 2.0, 4);
    step(&mut e, Action::MoveForward);
    assert!((e.agent_pose().position.x - 2.0).abs() < 1e-15);
    assert_eq!(e.agent_pose().position.z, 1.75);

    // Heading 2 (45°): the move is 0.25 m long.
    let mut e = open_room(2.0, 2.0, 2);
    step(&mut e, Action::MoveForward);
    let p = e.agent_pose().position;
    assert!(((p.x - 2.0).hypot(p.z - 2.0) - 0.25).abs() < 1e-12);
    assert!(p.x > 2.0 && p.z < 2.0);
}

#[test]
fn turns_change_the_heading_index_by_one() {
    let mut e = open_room(2.0, 2.0, 0);
    let o = step(&mut e, Action::TurnLeft);
    assert!(o.accepted);
    assert_eq!(e.agent_pose().heading.index(), 1);
    step(&mut e, Action::TurnRight);
    step(&mut e, Action::TurnRight);
    assert_eq!(e.agent_pose().heading.index(), 15);
    // A turn does not move the agent.
    assert_eq!(e.agent_pose().position.x, 2.0);
    assert_eq!(e.agent_pose().position.z, 2.0);
}

#[test]
fn a_rejected_motion_leaves_the_state_bit_identical_and_counts_as_a_step() {
    // Facing −x, 0.5 m from the wall at x = 0: one step would put the robot's edge past it.
    let mut e = open_room(0.5, 2.5, 8);
    let before = e.clone();
    let o = step(&mut e, Action::MoveForward);
    assert!(!o.accepted);
    assert_eq!(o.collided_with, Some(Obstacle::Wall(3)));
    assert!(e.same_state(&before));
    assert_eq!(e.revision(), before.revision());
    assert_eq!(o.step_index, 1);
    assert_eq!(e.steps(), 1);
    // Moving away is fine.
    assert!(step(&mut e, Action::MoveBackward).accepted);
}

#[test]
fn the_margin_is_respected() {
    // The robot's edge ends 0.005 m from the wall: inside the 0.01 m margin, so rejected.
    let mut e = open_room(0.555, 2.5, 8);
    assert!(!step(&mut e, Action::MoveForward).accepted);
    // 0.02 m from the wall: accepted.
    let mut e = open_room(0.57, 2.5, 8);
    assert!(step(&mut e, Action::MoveForward).accepted);
}

#[test]
fn a_rotation_that_collides_only_mid_arc_is_rejected() {
    // The agent at (3, 3) facing +x carries a 0.2 m bar 1 m ahead. A thin pole stands 1 m away
    // at 11.25° to the left: clear of the bar at 0° and at 22.5°, in its way at 11.25°.
    let angle = std::f64::consts::PI / 16.0;
    let pole = (3.0 + angle.cos(), 3.0 - angle.sin());
    let scene = SceneBuilder::room(6.0, 6.0)
        .agent(3.0, 3.0, 0)
        .fixed("pole", vec![cylinder_part(0.05, 1.0)], pole.0, pole.1, 0.0)
        .movable("bar", vec![box_part(0.1, 0.1, 0.6)], pose(4.0, 3.0, 0.0), pose(1.0, 1.0, 0.0))
        .compile();
    // Independent check with parry's intersection test: the bar is clear of the pole at both
    // ends of the turn and hits it half-way.
    let bar = scene.movable_shape(0);
    let world = scene.static_shape();
    let at = |a: f64| pose(3.0 + a.cos(), 3.0 - a.sin(), a);
    let hits =
        |a: f64| query::intersection_test(&object_pose(&at(a)), bar, &Pose::IDENTITY, world).unwrap().intersecting;
    assert!(!hits(0.0) && !hits(2.0 * angle));
    assert!(hits(angle));

    let mut e = Episode::new(scene, EpisodeConfig::default()).unwrap();
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
    let before = e.clone();
    let o = step(&mut e, Action::TurnLeft);
    assert!(!o.accepted, "the turn sweeps the bar through the pole");
    assert_eq!(o.collided_with, Some(Obstacle::Fixed(0)));
    assert!(e.same_state(&before));
    // Turning the other way is free.
    assert!(step(&mut e, Action::TurnRight).accepted);
}

#[test]
fn the_held_object_collides_too_and_names_the_obstacle() {
    // The agent carries a box ahead of it towards the wall at x = 5: the box hits first.
    let mut e = SceneBuilder::room(5.0, 5.0)
        .agent(3.0, 2.5, 0)
        .movable("box", small_box(), pose(4.0, 2.5, 0.0), pose(1.0, 1.0, 0.0))
        .episode();
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
    for _ in 0..3 {
        assert!(step(&mut e, Action::MoveForward).accepted);
    }
    let o = step(&mut e, Action::MoveForward);
    assert!(!o.accepted);
    assert_eq!(o.collided_with, Some(Obstacle::Wall(1)));
    assert_eq!(e.object_poses()[0].x, 4.75);
}

#[test]
fn movable_objects_are_obstacles() {
    // Facing +x with a box 0.5 m ahead of the robot's edge: one step leaves 0.25 m, the next
    // would touch it.
    let mut e = SceneBuilder::room(5.0, 5.0)
        .agent(2.0, 2.5, 0)
        .movable("a", small_box(), pose(3.0, 2.5, 0.0), pose(1.0, 1.0, 0.0))
        .movable("b", small_box(), pose(4.5, 4.5, 0.0), pose(1.0, 4.0, 0.0))
        .episode();
    assert!(step(&mut e, Action::MoveForward).accepted);
    let o = step(&mut e, Action::MoveForward);
    assert_eq!(o.collided_with, Some(Obstacle::Movable(0)));
}

#[test]
fn doors_collide_like_walls() {
    let mut scene = SceneBuilder::room(5.0, 5.0)
        .agent(0.5, 2.5, 8)
        .movable("box", small_box(), pose(4.5, 4.5, 0.0), pose(4.5, 0.5, 0.0))
        .build();
    // A door in wall 3 (x = 0) right in front of the agent.
    scene.room.openings.push(Opening {
        kind: OpeningKind::Door,
        wall: 3,
        offset: 2.0,
        width: 1.0,
        bottom: 0.0,
        top: 2.0,
    });
    let compiled = CompiledScene::shared(scene).unwrap();
    assert!(compiled.wall_pieces().iter().any(|p| p.kind == esrp_core::WallPieceKind::Door));
    let mut e = Episode::new(compiled, EpisodeConfig::default()).unwrap();
    assert_eq!(step(&mut e, Action::MoveForward).collided_with, Some(Obstacle::Wall(3)));
}

fn fetch_scene(objects: &[(f64, f64)]) -> Episode {
    let mut b = SceneBuilder::room(6.0, 6.0).agent(3.0, 3.0, 0);
    for (i, &(x, z)) in objects.iter().enumerate() {
        // Targets along the bottom wall, far from every start.
        b = b.movable(&format!("o{i}"), small_box(), pose(x, z, 0.0), pose(0.5 + i as f64, 5.5, 0.0));
    }
    b.episode()
}

#[test]
fn fetch_takes_the_nearest_then_the_best_aligned_then_the_first() {
    // Nearest wins even against a better bearing: object 0 at the side is 0.7 m away, object 1
    // straight ahead 0.8 m.
    let mut e = fetch_scene(&[(3.0, 2.1), (4.0, 3.0)]);
    assert_eq!(e.fetch_candidate(), Some(0));
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
    // Equal distances (0.8 m): the smaller absolute bearing (straight ahead) wins over index.
    let mut e = fetch_scene(&[(3.0, 2.0), (4.0, 3.0)]);
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(1));
    // Equal distances and equal absolute bearings (90° left and right): the smaller index.
    let mut e = fetch_scene(&[(3.0, 4.0), (3.0, 2.0)]);
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
}

#[test]
fn fetch_reach_is_a_closest_point_distance_of_one_metre() {
    // A 0.5 m box whose near face is exactly 1.0 m from the agent's centre: in reach (inclusive;
    // 1.000001 m is not).
    let at = |x: f64| {
        SceneBuilder::room(6.0, 6.0)
            .agent(3.0, 3.0, 0)
            .movable("box", vec![box_part(0.25, 0.25, 0.5)], pose(x, 3.0, 0.0), pose(1.0, 5.0, 0.0))
            .episode()
    };
    let mut e = at(4.25);
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
    assert_eq!(step(&mut at(4.250001), Action::Fetch).no_op, Some(NoOpReason::NothingInReach));
    // 1.05 m: out of reach, and fetch says why.
    let mut e = at(4.3);
    let o = step(&mut e, Action::Fetch);
    assert_eq!((o.accepted, o.fetched, o.no_op), (false, None, Some(NoOpReason::NothingInReach)));
    assert_eq!(e.held(), None);
    assert_eq!(e.steps(), 1);

    // A 1.2 × 0.2 m bar centred 1.5 m ahead: pointing at the agent its end is 0.9 m away (in
    // reach); turned 90° its side is 1.4 m away (out of reach). The footprint's yaw counts.
    let bar = |yaw: f64| {
        SceneBuilder::room(6.0, 6.0)
            .agent(2.0, 3.0, 0)
            .movable("bar", vec![box_part(0.6, 0.1, 0.5)], pose(3.5, 3.0, yaw), pose(1.0, 5.0, 0.0))
            .episode()
    };
    assert_eq!(bar(0.0).fetch_candidate(), Some(0));
    assert_eq!(bar(std::f64::consts::FRAC_PI_2).fetch_candidate(), None);
}

#[test]
fn fetch_while_holding_and_release_with_nothing_held_are_no_ops() {
    let mut e = fetch_scene(&[(4.0, 3.0)]);
    let o = step(&mut e, Action::Release);
    assert_eq!((o.accepted, o.no_op), (false, Some(NoOpReason::NothingHeld)));
    step(&mut e, Action::Fetch);
    let before = e.clone();
    let o = step(&mut e, Action::Fetch);
    assert_eq!((o.accepted, o.no_op), (false, Some(NoOpReason::AlreadyHolding)));
    assert!(e.same_state(&before));
}

#[test]
fn a_held_object_moves_rigidly_and_release_leaves_it_where_it_is() {
    let mut e = fetch_scene(&[(4.0, 3.0)]);
    step(&mut e, Action::Fetch);
    assert_eq!(e.held(), Some(0));
    step(&mut e, Action::MoveBackward);
    assert_eq!(e.object_poses()[0], pose(3.75, 3.0, 0.0));
    // A quarter turn left (4 × 22.5°) swings the box from +x to −z of the agent.
    for _ in 0..4 {
        assert!(step(&mut e, Action::TurnLeft).accepted);
    }
    let p = e.object_poses()[0];
    assert!((p.x - 2.75).abs() < 1e-12 && (p.z - 2.0).abs() < 1e-12, "{p:?}");
    assert!((p.yaw - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    let before = e.object_poses()[0];
    let o = step(&mut e, Action::Release);
    assert_eq!((o.accepted, o.released), (true, Some(0)));
    assert_eq!(e.held(), None);
    assert_eq!(e.object_poses()[0], before);
    // Moving on no longer moves the box.
    step(&mut e, Action::MoveBackward);
    assert_eq!(e.object_poses()[0], before);
}

#[test]
fn rewards_success_termination_and_metrics() {
    // The box starts 0.5 m short of its target (IoU 0) straight ahead of the agent.
    let mut e = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .movable("box", small_box(), pose(3.0, 2.0, 0.0), pose(3.5, 2.0, 0.0))
        .episode();
    assert_eq!(e.metrics().stage, Stage::NeverFetched);
    let o = step(&mut e, Action::Fetch);
    assert_eq!(o.reward.holding, 0.01);
    assert_eq!(o.reward.total, 0.01);
    let o = step(&mut e, Action::MoveForward);
    assert!((o.reward.potential - 0.25).abs() < 1e-12);
    assert!((o.reward.total - 0.26).abs() < 1e-12);
    let o = step(&mut e, Action::MoveForward);
    assert!((o.reward.potential - 0.25).abs() < 1e-12);
    let o = step(&mut e, Action::Release);
    assert_eq!(o.reward.placement, 1.0);
    assert_eq!(o.reward.success, 10.0);
    assert_eq!(o.reward.holding, 0.0);
    assert_eq!(o.reward.total, 11.0);
    assert!(o.terminated && !o.truncated);
    assert_eq!(o.placed_count, 1);
    let m = e.metrics();
    assert!(m.success);
    assert_eq!(m.stage, Stage::Succeeded);
    assert_eq!(m.object_success_rate, 1.0);
    assert_eq!(m.remaining_distance_ratio, 0.0);
    assert_eq!(m.steps, 4);
    assert!((m.total_reward - 11.53).abs() < 1e-12);
    match e.step(Action::MoveForward) {
        Err(EpisodeError::Finished { reason: "success", steps: 4 }) => {}
        other => panic!("stepping a finished episode must fail, got {other:?}"),
    }
}

#[test]
fn fetching_a_placed_object_costs_the_unplace_penalty() {
    // Object 0 starts on its target; object 1 does not.
    let mut e = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .movable("placed", small_box(), pose(3.0, 2.0, 0.0), pose(3.05, 2.0, 0.0))
        .movable("away", small_box(), pose(5.0, 5.0, 0.0), pose(1.0, 5.0, 0.0))
        .episode();
    assert_eq!(e.placed(), &[true, false]);
    let o = step(&mut e, Action::Fetch);
    assert_eq!(o.fetched, Some(0));
    assert_eq!(o.reward.placement, -1.0);
    assert_eq!(o.placed_count, 0);
    // Putting it back down on its target pays +1 but is not a success while object 1 is away.
    let o = step(&mut e, Action::Release);
    assert_eq!(o.reward.placement, 1.0);
    assert!(!o.terminated);
    assert_eq!(e.metrics().object_success_rate, 0.5);
}

#[test]
fn custom_reward_weights_apply() {
    let scene = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .movable("box", small_box(), pose(3.0, 2.0, 0.0), pose(3.5, 2.0, 0.0))
        .compile();
    let mut config = EpisodeConfig::default();
    config.reward.potential = 2.0;
    config.reward.living = -0.5;
    config.reward.holding = 0.0;
    let mut e = Episode::new(scene, config).unwrap();
    step(&mut e, Action::Fetch);
    let o = step(&mut e, Action::MoveForward);
    assert!((o.reward.potential - 0.5).abs() < 1e-12);
    assert_eq!(o.reward.living, -0.5);
    assert!((o.reward.total - 0.0).abs() < 1e-12);
}

#[test]
fn truncation_at_the_horizon_and_the_stages() {
    // Stage 1: the only object is far away; the agent only turns.
    let mut e = SceneBuilder::room(7.0, 7.0)
        .agent(1.0, 1.0, 0)
        .horizon(3)
        .movable("box", small_box(), pose(6.0, 6.0, 0.0), pose(6.0, 1.0, 0.0))
        .episode();
    assert_eq!(e.horizon(), 3);
    assert!(!step(&mut e, Action::TurnLeft).truncated);
    assert!(!step(&mut e, Action::TurnLeft).truncated);
    let o = step(&mut e, Action::TurnLeft);
    assert!(o.truncated && !o.terminated);
    let m = e.metrics();
    assert_eq!(
        (m.stage, m.success, m.object_success_rate, m.remaining_distance_ratio),
        (Stage::NeverReached, false, 0.0, 1.0)
    );
    assert!(matches!(e.step(Action::TurnLeft), Err(EpisodeError::Finished { reason: "horizon reached", .. })));

    // Stage 2: within reach, never fetched. Stage 3: fetched, not placed, RDR from the move.
    let scene = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 2.0, 0)
        .horizon(2)
        .movable("box", small_box(), pose(3.0, 2.0, 0.0), pose(4.0, 2.0, 0.0))
        .compile();
    let mut e = Episode::new(scene.clone(), EpisodeConfig::default()).unwrap();
    step(&mut e, Action::TurnLeft);
    step(&mut e, Action::TurnRight);
    assert_eq!(e.metrics().stage, Stage::NeverFetched);
    let config = EpisodeConfig { horizon: Some(3), ..Default::default() };
    let mut e = Episode::new(scene, config).unwrap();
    assert_eq!(e.horizon(), 3);
    step(&mut e, Action::Fetch);
    step(&mut e, Action::MoveForward);
    let o = step(&mut e, Action::MoveForward);
    assert!(o.truncated);
    let m = e.metrics();
    assert_eq!(m.stage, Stage::Fetched);
    assert!((m.remaining_distance_ratio - 0.5).abs() < 1e-12);
    assert_eq!(m.object_success_rate, 0.0);
}

#[test]
fn reset_restores_the_start() {
    let mut e = fetch_scene(&[(4.0, 3.0)]);
    let fresh = e.clone();
    step(&mut e, Action::Fetch);
    step(&mut e, Action::MoveBackward);
    e.reset();
    assert!(e.same_state(&fresh));
    assert_eq!(e.steps(), 0);
    assert_ne!(e.revision(), fresh.revision(), "renderers must see that the view changed");
}

#[test]
fn camera_and_privileged_state_describe_the_episode() {
    let mut e = fetch_scene(&[(4.0, 3.0)]);
    step(&mut e, Action::TurnLeft);
    let camera = e.ego_camera();
    assert_eq!(camera.eye, [3.0, 1.25, 3.0]);
    assert_eq!(camera.yaw, std::f64::consts::FRAC_PI_8);
    assert!((camera.pitch.to_degrees() - 20.0).abs() < 1e-12);
    assert!((camera.horizontal_fov.to_degrees() - 90.0).abs() < 1e-12);
    let state = e.privileged_state();
    assert_eq!(state.agent.heading.index(), 1);
    assert_eq!(state.objects.len(), 1);
    assert_eq!(state.objects[0].id, "o0");
    assert_eq!(state.objects[0].footprint.center.x, 4.0);
    assert_eq!(state.objects[0].iou, 0.0);
    // Four walls, no fixed object.
    assert_eq!(state.static_obstacles.len(), 4);
    assert!(state.static_obstacles.iter().all(|s| matches!(s.obstacle, Obstacle::Wall(_))));
}

#[test]
fn meshes_collide_as_triangles_when_fixed_and_as_hulls_when_movable() {
    let cube = |s: f64, h: f64| esrp_core::Mesh {
        vertices: vec![
            [-s, 0.0, -s],
            [s, 0.0, -s],
            [s, 0.0, s],
            [-s, 0.0, s],
            [-s, h, -s],
            [s, h, -s],
            [s, h, s],
            [-s, h, s],
        ],
        triangles: vec![
            [0, 2, 1],
            [0, 3, 2],
            [4, 5, 6],
            [4, 6, 7],
            [0, 1, 5],
            [0, 5, 4],
            [1, 2, 6],
            [1, 6, 5],
            [2, 3, 7],
            [2, 7, 6],
            [3, 0, 4],
            [3, 4, 7],
        ],
    };
    let mut scene: Scene = SceneBuilder::room(6.0, 6.0)
        .agent(2.0, 3.0, 0)
        .fixed("mesh-table", vec![box_part(0.1, 0.1, 0.1)], 3.0, 3.0, 0.0)
        .movable("mesh-box", small_box(), pose(2.25, 4.0, 0.0), pose(5.0, 1.0, 0.0))
        .build();
    scene.fixed_objects[0].shape = esrp_core::Shape::Mesh(cube(0.2, 0.6));
    scene.movable_objects[0].shape = esrp_core::Shape::Mesh(cube(0.2, 0.5));
    let mut e = Episode::new(CompiledScene::shared(scene).unwrap(), EpisodeConfig::default()).unwrap();
    // The robot's edge is 0.5 m from the mesh: one step approaches, the second would hit it.
    assert!(step(&mut e, Action::MoveForward).accepted);
    assert_eq!(step(&mut e, Action::MoveForward).collided_with, Some(Obstacle::Fixed(0)));
    // The movable mesh is fetched and carried like any object.
    for _ in 0..4 {
        step(&mut e, Action::TurnRight);
    }
    assert_eq!(step(&mut e, Action::Fetch).fetched, Some(0));
}
