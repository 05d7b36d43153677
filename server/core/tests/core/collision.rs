//! The collision module's public API: the same answers as `Episode::step`, asked without an
//! episode, and the fit, wall and clearance queries on hand-made scenes.

use std::sync::Arc;

use esrp_core::collision::{
    self, Body, Motion, MovableObstacles, object_obstruction, obstruction, robot_pose, separated, wall_collider,
    wall_pieces,
};
use esrp_core::parry3d::math::Pose;
use esrp_core::parry3d::shape::SharedShape;
use esrp_core::{
    Action, CompiledScene, Episode, EpisodeConfig, Heading, Layout, Obstacle, Opening, OpeningKind, PlanPoint, Rules,
    SceneError, TURN_ANGLE, WallPieceKind,
};

use super::fixtures::{SceneBuilder, box_part, pose, random_actions, random_scene, small_box};

/// A planner's view: the body and obstacles built from the episode's public state only.
fn planner_view(e: &Episode) -> (Body, MovableObstacles) {
    let poses = e.object_poses().to_vec();
    let body = Body { position: e.agent_pose().position, held: e.held().map(|i| (i, poses[i])) };
    (body, MovableObstacles::new(e.compiled(), poses))
}

#[test]
fn first_hit_is_the_rule_that_step_applies() {
    let (mut motions, mut hits, mut carried_hits) = (0, 0, 0);
    for seed in 0..32u64 {
        let scene = Arc::new(CompiledScene::new(random_scene(seed), Rules::default()).unwrap());
        let config = EpisodeConfig { horizon: Some(10_000), ..Default::default() };
        let mut e = Episode::new(scene.clone(), config).unwrap();
        for action in random_actions(seed, 80) {
            let motion = Motion::of(action, e.agent_pose().heading);
            let (body, obstacles) = planner_view(&e);
            assert_eq!(body, e.body());
            assert_eq!(&obstacles.poses(), &e.obstacles().poses());
            let predicted = motion.and_then(|m| collision::first_hit(&scene, &obstacles, &body, m));
            let from_episode = motion.and_then(|m| collision::first_hit(&scene, e.obstacles(), &e.body(), m));
            // Bit-identical, time of impact included.
            assert_eq!(
                predicted.map(|h| (h.time.to_bits(), h.obstacle)),
                from_episode.map(|h| (h.time.to_bits(), h.obstacle))
            );
            let outcome = e.step(action).unwrap();
            assert_eq!(outcome.collided_with, predicted.map(|h| h.obstacle), "seed {seed}: {action:?}");
            if let Some(m) = motion {
                motions += 1;
                assert_eq!(outcome.accepted, predicted.is_none());
                hits += usize::from(predicted.is_some());
                carried_hits += usize::from(predicted.is_some() && body.held.is_some());
                if let Some(hit) = predicted {
                    assert!((0.0..=1.0).contains(&hit.time), "seed {seed}: {m:?} hit at {}", hit.time);
                } else {
                    // A free motion ends where the body fits.
                    assert_eq!(obstruction(&scene, e.object_poses(), &e.body()), None, "seed {seed}: {action:?}");
                }
            }
        }
    }
    assert!(motions > 1000 && hits > 50 && carried_hits > 10, "{motions} motions, {hits} hits, {carried_hits} carried");
}

#[test]
fn motions_have_the_arithmetic_of_step() {
    for k in 0..16 {
        let mut e = SceneBuilder::room(5.0, 5.0)
            .agent(2.5, 2.5, k)
            .movable("box", small_box(), pose(4.6, 4.6, 0.0), pose(4.6, 0.4, 0.0))
            .episode();
        let heading = Heading::new(k).unwrap();
        let Some(Motion::Translate(d)) = Motion::of(Action::MoveForward, heading) else { panic!("a move translates") };
        assert!(e.step(Action::MoveForward).unwrap().accepted);
        let p = e.agent_pose().position;
        assert_eq!((p.x, p.z), (2.5 + d.x, 2.5 + d.z), "heading {k}");
        let Some(Motion::Translate(back)) = Motion::of(Action::MoveBackward, heading) else { panic!() };
        assert_eq!((back.x, back.z), (-d.x, -d.z));
    }
    let h = Heading::new(3).unwrap();
    assert_eq!(Motion::of(Action::TurnLeft, h), Some(Motion::Rotate(TURN_ANGLE)));
    assert_eq!(Motion::of(Action::TurnRight, h), Some(Motion::Rotate(-TURN_ANGLE)));
    assert_eq!(Motion::of(Action::Fetch, h), None);
    assert_eq!(Motion::of(Action::Release, h), None);
}

#[test]
fn a_planner_asks_about_a_move_without_an_episode() {
    // The agent at (3, 2.5) facing +x; a box at (4.5, 2.5) with its near face at 4.3.
    let scene = SceneBuilder::room(6.0, 5.0)
        .agent(1.0, 1.0, 0)
        .movable("box", small_box(), pose(4.5, 2.5, 0.0), pose(1.0, 4.0, 0.0))
        .movable("bar", vec![box_part(0.1, 0.1, 0.6)], pose(1.0, 4.2, 0.0), pose(5.0, 1.0, 0.0))
        .compile();
    let poses = scene.scene().movable_objects.iter().map(|o| o.pose).collect::<Vec<_>>();
    let obstacles = MovableObstacles::new(&scene, poses.clone());
    let forward = Motion::of(Action::MoveForward, Heading::new(0).unwrap()).unwrap();
    // The robot's edge at 3.3 + 0.25 stays 0.75 m short of the box: free.
    assert_eq!(collision::first_hit(&scene, &obstacles, &Body::robot(PlanPoint::new(3.0, 2.5)), forward), None);
    // From 3.8 the edge would reach 4.35, past the box's face at 4.3: it hits the box after
    // 0.2 − 0.01 (the margin) of the 0.25 m.
    let hit = collision::first_hit(&scene, &obstacles, &Body::robot(PlanPoint::new(3.8, 2.5)), forward).unwrap();
    assert_eq!(hit.obstacle, Obstacle::Movable(0));
    assert!((hit.time - 0.19 / 0.25).abs() < 1e-6, "time {}", hit.time);
    // Holding the box, the robot does not hit it; the box itself is carried into the wall at 6.
    let held = Body { position: PlanPoint::new(3.8, 2.5), held: Some((0, poses[0])) };
    assert_eq!(collision::first_hit(&scene, &obstacles, &held, forward), None);
    let near_wall = Body { position: PlanPoint::new(5.0, 2.5), held: Some((0, pose(5.6, 2.5, 0.0))) };
    let hit = collision::first_hit(&scene, &obstacles, &near_wall, forward).unwrap();
    assert_eq!(hit.obstacle, Obstacle::Wall(1));
    // Moving another object changes the answer: the box moved out of the way frees the move.
    let mut moved = obstacles.clone();
    moved.set(&scene, 0, pose(4.5, 0.5, 0.0));
    assert_eq!(moved.poses()[0], pose(4.5, 0.5, 0.0));
    assert_eq!(collision::first_hit(&scene, &moved, &Body::robot(PlanPoint::new(3.8, 2.5)), forward), None);
    // Turning left (towards −z) with the bar held 1 m ahead, 0.1 m beside the box, sweeps the
    // bar through the box, and through nothing once the box is moved; the robot alone, a
    // cylinder turning about its axis, sweeps nothing new.
    let turn = Motion::of(Action::TurnLeft, Heading::new(0).unwrap()).unwrap();
    assert_eq!(collision::first_hit(&scene, &obstacles, &Body::robot(PlanPoint::new(3.8, 2.5)), turn), None);
    let bar = Body { position: PlanPoint::new(3.6, 2.9), held: Some((1, pose(4.6, 2.9, 0.0))) };
    assert_eq!(collision::first_hit(&scene, &obstacles, &bar, turn).map(|h| h.obstacle), Some(Obstacle::Movable(0)));
    assert_eq!(collision::first_hit(&scene, &moved, &bar, turn), None);
}

#[test]
fn a_body_fits_only_clear_of_everything_by_the_margin() {
    let scene = SceneBuilder::room(5.0, 5.0)
        .agent(2.5, 2.5, 0)
        .fixed("table", vec![box_part(0.4, 0.4, 0.7)], 1.0, 4.0, 0.0)
        .movable("box", small_box(), pose(4.0, 1.0, 0.0), pose(4.0, 4.0, 0.0))
        .compile();
    let poses = [pose(4.0, 1.0, 0.0)];
    let robot = |x: f64, z: f64| Body::robot(PlanPoint::new(x, z));
    assert_eq!(obstruction(&scene, &poses, &robot(2.5, 2.5)), None);
    // 0.005 m from the wall at x = 0: inside the 0.01 m margin.
    assert_eq!(obstruction(&scene, &poses, &robot(0.305, 2.5)), Some(Obstacle::Wall(3)));
    assert_eq!(obstruction(&scene, &poses, &robot(0.32, 2.5)), None);
    // The table's face is at z = 3.6, the box's at x = 3.8.
    assert_eq!(obstruction(&scene, &poses, &robot(1.0, 3.295)), Some(Obstacle::Fixed(0)));
    assert_eq!(obstruction(&scene, &poses, &robot(1.0, 3.28)), None);
    assert_eq!(obstruction(&scene, &poses, &robot(3.495, 1.0)), Some(Obstacle::Movable(0)));
    // Held, the box is no obstacle to the robot, but it is one to the walls.
    let holding = |x: f64, z: f64| Body { position: PlanPoint::new(3.0, 1.0), held: Some((0, pose(x, z, 0.0))) };
    assert_eq!(obstruction(&scene, &poses, &holding(3.5, 1.0)), None);
    assert_eq!(obstruction(&scene, &poses, &holding(3.5, 0.205)), Some(Obstacle::Wall(0)));
    // An object alone: the check of a layout.
    assert_eq!(object_obstruction(&scene, &poses, 0, &pose(4.0, 1.0, 0.0)), None);
    assert_eq!(object_obstruction(&scene, &poses, 0, &pose(1.0, 3.5, 0.0)), Some(Obstacle::Fixed(0)));
    assert_eq!(robot_pose(PlanPoint::new(1.0, 2.0)).translation.y, esrp_core::world::ROBOT_HEIGHT / 2.0);
}

#[test]
fn object_obstruction_is_the_layout_check_of_compilation() {
    let builder = SceneBuilder::room(5.0, 5.0)
        .agent(1.0, 1.0, 0)
        .movable("a", small_box(), pose(3.0, 3.0, 0.0), pose(1.0, 4.0, 0.0))
        .movable("b", small_box(), pose(3.0, 1.0, 0.0), pose(4.0, 4.0, 0.0));
    let scene = builder.clone().compile();
    // b 0.405 m beside a: 0.005 m apart, inside the margin; 0.42: clear.
    let poses = [pose(3.0, 3.0, 0.0), pose(3.405, 3.0, 0.0)];
    assert_eq!(object_obstruction(&scene, &poses, 1, &poses[1]), Some(Obstacle::Movable(0)));
    assert_eq!(object_obstruction(&scene, &poses, 1, &pose(3.42, 3.0, 0.0)), None);
    let mut overlapping = builder.build();
    overlapping.movable_objects[1].pose = poses[1];
    match CompiledScene::new(overlapping, Rules::default()) {
        Err(SceneError::Overlap { object, other, layout: Layout::Initial, .. }) => {
            assert_eq!((object.as_str(), other.as_str()), ("a", "b"));
        }
        other => panic!("expected an overlap, got {other:?}"),
    }
}

#[test]
fn wall_pieces_are_the_walls_of_the_compiled_scene() {
    let door = Opening { wall: 0, offset: 1.0, width: 0.9, bottom: 0.0, top: 2.0, kind: OpeningKind::Door };
    let window = Opening { wall: 2, offset: 1.5, width: 1.0, bottom: 0.9, top: 1.8, kind: OpeningKind::Window };
    let mut builder = SceneBuilder::room(5.0, 4.0).agent(2.5, 2.0, 0).movable(
        "box",
        small_box(),
        pose(4.0, 1.0, 0.0),
        pose(4.0, 3.0, 0.0),
    );
    builder.scene.room.openings = vec![window.clone(), door.clone()];
    let scene = builder.compile();
    let room = &scene.scene().room;
    let pieces = wall_pieces(scene.floor(), room.wall_thickness, room.wall_height, &room.openings);
    assert_eq!(pieces, scene.wall_pieces());
    // Walls 1 and 3 whole; the door's wall in three pieces and its leaf; the window's in four.
    assert_eq!(pieces.len(), 1 + 1 + 4 + 4);
    assert_eq!(pieces.iter().filter(|p| p.kind == WallPieceKind::Door).count(), 1);
    let statics = scene.static_shape().shapes();
    for (k, piece) in pieces.iter().enumerate() {
        let (pose, shape) = wall_collider(piece);
        assert_eq!(pose, statics[k].0);
        assert_eq!(shape.compute_local_aabb(), statics[k].1.compute_local_aabb());
        assert_eq!(scene.static_part_owner(k as u32), Obstacle::Wall(piece.wall));
    }
    // Every wall is outside the floor: its inner face lies on the floor's edge.
    let solid = wall_pieces(scene.floor(), 0.12, 2.6, &[]);
    assert_eq!(solid.len(), 4);
    let west = solid.iter().find(|p| p.wall == 3).unwrap();
    assert!((west.center[0] + 0.06).abs() < 1e-12 && (west.half_extents[0] - 2.12).abs() < 1e-12);
    // The same room drawn clockwise has the same walls.
    let clockwise: Vec<PlanPoint> = scene.floor().iter().rev().copied().collect();
    let reversed = wall_pieces(&clockwise, 0.12, 2.6, &[]);
    assert_eq!(reversed.len(), 4);
    for piece in &solid {
        assert!(reversed.iter().any(|r| (0..3).all(|k| (r.center[k] - piece.center[k]).abs() < 1e-12)));
    }
    // An opening on a wall the floor does not have is ignored.
    let stray = Opening { wall: 9, ..door.clone() };
    assert_eq!(wall_pieces(scene.floor(), 0.12, 2.6, &[stray]), solid);
}

#[test]
fn separated_measures_clearance_between_exact_shapes() {
    let cube = SharedShape::cuboid(0.5, 0.5, 0.5);
    let at = |x: f64| Pose::translation(x, 0.0, 0.0);
    // Faces 0.05 m apart.
    assert!(separated(&at(0.0), cube.as_ref(), &at(1.05), cube.as_ref(), 0.02));
    assert!(separated(&at(0.0), cube.as_ref(), &at(1.05), cube.as_ref(), 0.049));
    assert!(!separated(&at(0.0), cube.as_ref(), &at(1.05), cube.as_ref(), 0.06));
    // Overlapping, and far apart (answered by the boxes alone).
    assert!(!separated(&at(0.0), cube.as_ref(), &at(0.5), cube.as_ref(), 0.01));
    assert!(separated(&at(0.0), cube.as_ref(), &at(10.0), cube.as_ref(), 0.02));
}
