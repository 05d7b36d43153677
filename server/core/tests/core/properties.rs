//! Property tests over random valid scenes and random action sequences (SPEC §3–5).

use esrp_core::collision::{self, Body, object_pose, robot_pose};
use esrp_core::parry3d::math::Pose;
use esrp_core::parry3d::query;
use esrp_core::{
    Action, CompiledScene, Episode, EpisodeConfig, ObjectPose, OrientedRect, PlanPoint, Rules, footprint_iou,
};
use proptest::prelude::*;
use std::sync::Arc;

use super::fixtures::{SplitMix, random_actions, random_scene};

/// Whether the robot (at `position`) or the held object (at `held_pose`) intersects any
/// obstacle, by parry's intersection test on the exact shapes: independent of the casts that
/// the simulator uses.
fn body_intersects(
    scene: &CompiledScene,
    position: PlanPoint,
    held: Option<(usize, ObjectPose)>,
    poses: &[ObjectPose],
) -> Option<String> {
    let world = scene.static_shape();
    let mut body: Vec<(Pose, &dyn esrp_core::parry3d::shape::Shape, String)> =
        vec![(robot_pose(position), scene.robot_shape().as_ref(), "robot".into())];
    if let Some((i, pose)) = held {
        body.push((object_pose(&pose), scene.movable_shape(i), format!("held object {i}")));
    }
    for (pose, shape, name) in &body {
        if query::intersection_test(pose, *shape, &Pose::IDENTITY, world).unwrap().intersecting {
            return Some(format!("{name} intersects the static world"));
        }
        for (j, other) in poses.iter().enumerate() {
            if held.is_some_and(|(i, _)| i == j) {
                continue;
            }
            if query::intersection_test(pose, *shape, &object_pose(other), scene.movable_shape(j)).unwrap().intersecting
            {
                return Some(format!("{name} intersects movable object {j}"));
            }
        }
    }
    None
}

fn episode(seed: u64) -> Episode {
    let scene = Arc::new(CompiledScene::new(random_scene(seed), Rules::default()).unwrap());
    let config = EpisodeConfig { horizon: Some(10_000), ..Default::default() };
    Episode::new(scene, config).unwrap()
}

/// A point `(x, z)` rotated by `yaw` about the origin (SPEC §1 convention).
fn rotated(x: f64, z: f64, yaw: f64) -> (f64, f64) {
    let (s, c) = yaw.sin_cos();
    (c * x + s * z, -s * x + c * z)
}

fn rect() -> impl Strategy<Value = OrientedRect> {
    (-2.0..2.0f64, -2.0..2.0f64, 0.05..1.5f64, 0.05..1.5f64, -4.0..4.0f64)
        .prop_map(|(x, z, hx, hz, yaw)| OrientedRect { center: PlanPoint::new(x, z), half_x: hx, half_z: hz, yaw })
}

fn contains(r: &OrientedRect, x: f64, z: f64) -> bool {
    let (lx, lz) = rotated(x - r.center.x, z - r.center.z, -r.yaw);
    lx.abs() <= r.half_x && lz.abs() <= r.half_z
}

/// Walks `count` random actions of `seed`'s scene and checks property (a): after every accepted
/// action the exact body is clear of every obstacle, and along every accepted turn the body
/// dilated by the margin is clear at 64 poses of the arc (the rule the rotational cast decides,
/// checked by intersection tests instead).
fn walk_checking_contacts(seed: u64, count: usize) -> Result<(), String> {
    let mut e = episode(seed);
    let scene = e.compiled().clone();
    for action in random_actions(seed, count) {
        if e.is_over() {
            break;
        }
        let before = e.clone();
        let outcome = e.step(action).unwrap();
        if !outcome.accepted {
            continue;
        }
        let held = e.held().map(|i| (i, e.object_poses()[i]));
        if let Some(problem) = body_intersects(&scene, e.agent_pose().position, held, e.object_poses()) {
            return Err(format!("seed {seed}: after {action:?}: {problem}"));
        }
        if matches!(action, Action::TurnLeft | Action::TurnRight) {
            let sign = if action == Action::TurnLeft { 1.0 } else { -1.0 };
            let centre = before.agent_pose().position;
            for k in 1..64 {
                let angle = sign * esrp_core::TURN_ANGLE * f64::from(k) / 64.0;
                let held = before.held().map(|i| {
                    let p = before.object_poses()[i];
                    let (dx, dz) = rotated(p.x - centre.x, p.z - centre.z, angle);
                    (i, ObjectPose::new(centre.x + dx, centre.z + dz, p.yaw + angle))
                });
                let body = Body { position: centre, held };
                if let Some(obstacle) = collision::obstruction(&scene, before.object_poses(), &body) {
                    return Err(format!(
                        "seed {seed}: {action:?} passes within the margin of {obstacle:?} at {k}/64 of the arc"
                    ));
                }
            }
        }
    }
    Ok(())
}

/// Walks where parry's nonlinear shape cast, which the turns used before, let a carried object
/// pass through another in the middle of a turn whose two ends were clear (so the turn back was
/// rejected): the rotational cast must reject those turns.
#[test]
fn turns_are_checked_along_the_whole_arc() {
    for seed in [18_371_815_817_542_484_691, 12_773_090_487_639_266_955, 8_146_607_701_191_617_292] {
        walk_checking_contacts(seed, 200).unwrap();
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    /// (a) After every accepted action, neither the robot nor the held object intersects an
    /// obstacle; and for every accepted turn, no pose along the arc comes within the margin of
    /// one (sampled).
    #[test]
    fn accepted_actions_never_end_in_contact(seed in any::<u64>()) {
        walk_checking_contacts(seed, 80).map_err(TestCaseError::fail)?;
    }

    /// (b) An accepted motion followed by its inverse restores the exact state.
    #[test]
    fn motions_are_exactly_reversible(seed in any::<u64>()) {
        let mut e = episode(seed);
        let mut reversed = 0;
        for action in random_actions(seed, 80) {
            if e.is_over() {
                break;
            }
            if !action.is_motion() {
                // Fetches and releases change what is carried; keep them in the walk.
                e.step(action).unwrap();
                continue;
            }
            let before = e.clone();
            if e.step(action).unwrap().accepted {
                let back = e.step(action.inverse()).unwrap();
                prop_assert!(back.accepted, "seed {}: the inverse of an accepted {:?} was rejected: {:?}", seed, action, back);
                prop_assert!(e.same_state(&before), "seed {}: {:?} then its inverse did not restore the state", seed, action);
                reversed += 1;
                // Then go on from the moved state.
                e.step(action).unwrap();
            }
        }
        prop_assert!(reversed > 0 || e.steps() > 0);
    }

    /// (d) Determinism: the same scene and actions give identical states, step by step, in two
    /// independently built episodes and in a clone.
    #[test]
    fn same_scene_and_actions_give_the_same_state(seed in any::<u64>()) {
        let mut a = episode(seed);
        let mut b = episode(seed);
        let actions = random_actions(seed, 60);
        let mut c = a.clone();
        for &action in &actions {
            if a.is_over() {
                prop_assert!(b.is_over() && c.is_over());
                break;
            }
            let oa = a.step(action).unwrap();
            let ob = b.step(action).unwrap();
            let oc = c.step(action).unwrap();
            prop_assert_eq!(oa, ob);
            prop_assert_eq!(oa, oc);
            prop_assert_eq!(a.state_fingerprint(), b.state_fingerprint());
            prop_assert_eq!(a.state_fingerprint(), c.state_fingerprint());
        }
        prop_assert_eq!(a.metrics(), b.metrics());
    }

    /// (e) `pose_after` predicts, bit for bit, the pose every accepted action leads to.
    #[test]
    fn pose_after_is_the_pose_an_accepted_action_leads_to(seed in any::<u64>()) {
        let mut e = episode(seed);
        for action in random_actions(seed, 80) {
            if e.is_over() {
                break;
            }
            let predicted = e.pose_after(action);
            if e.step(action).unwrap().accepted {
                prop_assert_eq!(e.agent_pose(), predicted, "seed {}: {:?}", seed, action);
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// (c) IoU is symmetric, in [0, 1], 1 for identical footprints, and agrees with a
    /// Monte-Carlo estimate within 0.02.
    #[test]
    fn iou_is_symmetric_bounded_and_matches_monte_carlo(a in rect(), b in rect(), seed in any::<u64>()) {
        let iou = footprint_iou(&a, &b);
        prop_assert!((0.0..=1.0).contains(&iou));
        prop_assert!((iou - footprint_iou(&b, &a)).abs() < 1e-12);
        prop_assert!((footprint_iou(&a, &a) - 1.0).abs() < 1e-12);
        // Sample the bounding box of both rectangles uniformly.
        let corners: Vec<PlanPoint> = a.corners().into_iter().chain(b.corners()).collect();
        let (min_x, max_x) = corners.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| (lo.min(p.x), hi.max(p.x)));
        let (min_z, max_z) = corners.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| (lo.min(p.z), hi.max(p.z)));
        let mut rng = SplitMix(seed);
        let (mut both, mut either) = (0u32, 0u32);
        for _ in 0..40_000 {
            let x = rng.range(min_x, max_x);
            let z = rng.range(min_z, max_z);
            let (in_a, in_b) = (contains(&a, x, z), contains(&b, x, z));
            both += u32::from(in_a && in_b);
            either += u32::from(in_a || in_b);
        }
        let estimate = f64::from(both) / f64::from(either.max(1));
        prop_assert!((estimate - iou).abs() < 0.02, "exact {} vs Monte-Carlo {}", iou, estimate);
    }
}

#[test]
fn the_example_scene_replays_to_success() {
    let scene = esrp_core::Scene::from_json(include_str!("../../examples/scenes/bedroom.json")).unwrap();
    let compiled = CompiledScene::shared(scene).unwrap();
    let mut e = Episode::new(compiled.clone(), EpisodeConfig::default()).unwrap();
    for &action in &compiled.scene().expert_trajectory {
        e.step(action).unwrap();
    }
    let m = e.metrics();
    assert!(m.success && m.object_success_rate == 1.0 && m.stage == esrp_core::Stage::Succeeded);
}

/// The random walks above must reach the interesting cases, or the properties prove little:
/// fetches, carried motions, collisions with walls, fixed and movable objects, and turns
/// rejected while carrying.
#[test]
fn random_walks_exercise_every_path() {
    use esrp_core::Obstacle;
    let (mut fetches, mut carried_moves, mut walls, mut fixed, mut movables, mut carried_turn_rejections) =
        (0, 0, 0, 0, 0, 0);
    for seed in 0..64u64 {
        let mut e = episode(seed);
        for action in random_actions(seed, 80) {
            if e.is_over() {
                break;
            }
            let holding = e.held().is_some();
            let o = e.step(action).unwrap();
            fetches += usize::from(o.fetched.is_some());
            carried_moves += usize::from(holding && o.accepted && action.is_motion());
            match o.collided_with {
                Some(Obstacle::Wall(_)) => walls += 1,
                Some(Obstacle::Fixed(_)) => fixed += 1,
                Some(Obstacle::Movable(_)) => movables += 1,
                None => {}
            }
            carried_turn_rejections +=
                usize::from(holding && o.collided() && matches!(action, Action::TurnLeft | Action::TurnRight));
        }
    }
    let counts = [fetches, carried_moves, walls, fixed, movables, carried_turn_rejections];
    eprintln!("path counts: {counts:?}");
    assert!(
        counts.iter().all(|&c| c >= 3),
        "fetches, carried moves, wall/fixed/movable hits, carried turn rejections: {counts:?}"
    );
}
