//! Scene validation: every kind of bad input gives its own typed error, never a panic.

use esrp_core::{CompiledScene, Layout, MAX_SCENE_NUMBER, Opening, OpeningKind, Part, Rules, Scene, SceneError, Shape};
use proptest::prelude::*;

use super::fixtures::{SceneBuilder, box_part, pose, random_scene, small_box};

/// A valid two-object scene to break in one place at a time.
fn base() -> Scene {
    SceneBuilder::room(5.0, 4.0)
        .agent(1.0, 1.0, 0)
        .fixed("table", vec![box_part(0.4, 0.4, 0.7)], 4.0, 3.0, 0.0)
        .movable("a", small_box(), pose(2.5, 1.0, 0.0), pose(2.5, 3.0, 0.0))
        .movable("b", small_box(), pose(1.0, 3.0, 0.0), pose(3.5, 1.0, 0.3))
        .build()
}

fn check(mutate: impl FnOnce(&mut Scene), expected: impl Fn(&SceneError) -> bool) {
    let mut scene = base();
    mutate(&mut scene);
    match CompiledScene::new(scene, Rules::default()) {
        Ok(_) => panic!("the broken scene was accepted"),
        Err(e) => {
            assert!(expected(&e), "unexpected error: {e:?}");
            // Every message says something a person can act on.
            assert!(e.to_string().len() > 20, "message too short: {e}");
        }
    }
}

#[test]
fn the_base_scene_is_valid() {
    CompiledScene::new(base(), Rules::default()).unwrap();
}

#[test]
fn schema_and_fields() {
    check(
        |s| s.schema = "esrp.scene/v2".into(),
        |e| matches!(e, SceneError::UnknownSchema { found } if found == "esrp.scene/v2"),
    );
    check(|s| s.id.clear(), |e| matches!(e, SceneError::EmptyField { .. }));
    check(|s| s.horizon = 0, |e| matches!(e, SceneError::ZeroHorizon));
    check(
        |s| s.movable_objects[1].id = "table".into(),
        |e| matches!(e, SceneError::DuplicateId { id } if id == "table"),
    );
    check(
        |s| s.difficulty = esrp_core::Difficulty::Hard,
        |e| matches!(e, SceneError::DifficultyMismatch { count: 2, .. }),
    );
}

#[test]
fn non_finite_numbers_name_their_field() {
    check(
        |s| s.movable_objects[1].pose.x = f64::NAN,
        |e| matches!(e, SceneError::NonFinite { path } if path == "movable_objects[1].pose"),
    );
    check(
        |s| s.movable_objects[0].target.yaw = f64::INFINITY,
        |e| matches!(e, SceneError::NonFinite { path } if path == "movable_objects[0].target"),
    );
    check(
        |s| s.room.floor[2][1] = f64::NEG_INFINITY,
        |e| matches!(e, SceneError::NonFinite { path } if path == "room.floor[2]"),
    );
    check(|s| s.agent.z = f64::NAN, |e| matches!(e, SceneError::NonFinite { path } if path == "agent"));
    check(
        |s| {
            s.fixed_objects[0].shape =
                Shape::Parts(vec![Part::Box { half_extents: [0.1, f64::NAN, 0.1], offset: [0.0; 3], yaw: 0.0 }])
        },
        |e| matches!(e, SceneError::NonFinite { path } if path == "fixed_objects[0].shape.parts[0].half_extents"),
    );
}

#[test]
fn numbers_beyond_any_room_name_their_field() {
    // A fixed box of half extent 1e308 was accepted, and a few steps later parry's EPA panicked.
    check(
        |s| {
            s.fixed_objects[0].shape =
                Shape::Parts(vec![Part::Box { half_extents: [0.4, 1e308, 0.4], offset: [0.0; 3], yaw: 0.0 }])
        },
        |e| {
            matches!(e, SceneError::OutOfRange { path, value, max }
                if path == "fixed_objects[0].shape.parts[0].half_extents" && *value == 1e308 && *max == MAX_SCENE_NUMBER)
        },
    );
    check(
        |s| s.movable_objects[0].pose.yaw = 1e9,
        |e| matches!(e, SceneError::OutOfRange { path, .. } if path == "movable_objects[0].pose"),
    );
    check(
        |s| s.room.floor[1][0] = -2e3,
        |e| matches!(e, SceneError::OutOfRange { path, .. } if path == "room.floor[1]"),
    );
    // The bound itself is accepted where the geometry allows it: a yaw of exactly 1,000 rad.
    let mut scene = base();
    scene.fixed_objects[0].pose.yaw = MAX_SCENE_NUMBER;
    CompiledScene::new(scene, Rules::default()).unwrap();
}

#[test]
fn object_counts() {
    check(|s| s.movable_objects.clear(), |e| matches!(e, SceneError::NoMovableObjects));
    check(
        |s| {
            let extra = s.movable_objects[0].clone();
            for i in 0..5 {
                let mut o = extra.clone();
                o.id = format!("extra-{i}");
                s.movable_objects.push(o);
            }
        },
        |e| matches!(e, SceneError::TooManyMovableObjects { count: 7 }),
    );
}

#[test]
fn shapes_must_be_solid() {
    check(
        |s| s.movable_objects[0].shape = Shape::Parts(vec![]),
        |e| matches!(e, SceneError::InvalidShape { object, .. } if object == "a"),
    );
    check(
        |s| {
            s.movable_objects[0].shape =
                Shape::Parts(vec![Part::Box { half_extents: [0.2, 0.0, 0.2], offset: [0.0; 3], yaw: 0.0 }])
        },
        |e| matches!(e, SceneError::InvalidShape { .. }),
    );
    check(
        |s| {
            s.movable_objects[0].shape =
                Shape::Parts(vec![Part::Cylinder { radius: -0.1, half_height: 0.2, offset: [0.0; 3], yaw: 0.0 }])
        },
        |e| matches!(e, SceneError::InvalidShape { .. }),
    );
    // Four points in one plane have no volume.
    let flat = vec![[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.2, 0.0, 0.2], [0.0, 0.0, 0.2]];
    check(
        |s| {
            s.movable_objects[1].shape =
                Shape::Parts(vec![Part::ConvexHull { points: flat, offset: [0.0; 3], yaw: 0.0 }])
        },
        |e| matches!(e, SceneError::InvalidShape { object, .. } if object == "b"),
    );
    check(
        |s| {
            s.fixed_objects[0].shape =
                Shape::Mesh(esrp_core::Mesh { vertices: vec![[0.0; 3]], triangles: vec![[0, 1, 2]] })
        },
        |e| matches!(e, SceneError::InvalidShape { reason, .. } if reason.contains("vertex 1")),
    );
    check(
        |s| s.fixed_objects[0].shape = Shape::Mesh(esrp_core::Mesh { vertices: vec![], triangles: vec![] }),
        |e| matches!(e, SceneError::InvalidShape { .. }),
    );
}

#[test]
fn rooms_and_openings() {
    check(|s| s.room.floor.truncate(2), |e| matches!(e, SceneError::InvalidRoom { .. }));
    check(
        |s| s.room.floor = vec![[0.0, 0.0], [5.0, 4.0], [5.0, 0.0], [0.0, 4.0]],
        |e| matches!(e, SceneError::InvalidRoom { .. }),
    );
    check(|s| s.room.wall_height = 0.5, |e| matches!(e, SceneError::InvalidRoom { .. }));
    let door = |wall: usize, offset: f64, width: f64| Opening {
        kind: OpeningKind::Door,
        wall,
        offset,
        width,
        bottom: 0.0,
        top: 2.0,
    };
    check(|s| s.room.openings.push(door(4, 0.5, 0.9)), |e| matches!(e, SceneError::InvalidOpening { index: 0, .. }));
    check(|s| s.room.openings.push(door(0, 4.5, 0.9)), |e| matches!(e, SceneError::InvalidOpening { index: 0, .. }));
    check(
        |s| {
            s.room.openings.push(door(0, 0.5, 0.9));
            s.room.openings.push(door(0, 1.0, 0.9));
        },
        |e| matches!(e, SceneError::InvalidOpening { .. }),
    );
    check(
        |s| {
            s.room.openings.push(Opening {
                kind: OpeningKind::Window,
                wall: 1,
                offset: 0.5,
                width: 1.0,
                bottom: 1.5,
                top: 1.0,
            })
        },
        |e| matches!(e, SceneError::InvalidOpening { .. }),
    );
}

#[test]
fn objects_and_agent_must_be_inside_and_clear() {
    check(
        |s| s.movable_objects[0].pose.x = 7.0,
        |e| matches!(e, SceneError::OutsideRoom { object, layout: Layout::Initial } if object == "a"),
    );
    check(
        |s| s.movable_objects[1].target.z = -1.0,
        |e| matches!(e, SceneError::OutsideRoom { object, layout: Layout::Target } if object == "b"),
    );
    check(
        |s| s.fixed_objects[0].pose.x = 9.0,
        |e| matches!(e, SceneError::OutsideRoom { object, .. } if object == "table"),
    );
    // Overlapping another movable object, a fixed one, a wall; and too close for the margin.
    check(
        |s| s.movable_objects[1].pose = pose(2.7, 1.1, 0.0),
        |e| matches!(e, SceneError::Overlap { layout: Layout::Initial, .. }),
    );
    check(
        |s| s.movable_objects[0].target = pose(3.8, 2.8, 0.0),
        |e| matches!(e, SceneError::Overlap { object, other, layout: Layout::Target, .. } if object == "a" && other == "table"),
    );
    check(
        |s| s.movable_objects[0].pose = pose(4.85, 1.0, 0.0),
        |e| matches!(e, SceneError::Overlap { other, .. } if other == "wall 1"),
    );
    // 5 mm from `b`: not touching, but inside the 10 mm margin.
    check(
        |s| s.movable_objects[0].pose = pose(1.0, 3.0 - 0.4 - 0.005, 0.0),
        |e| matches!(e, SceneError::Overlap { object, other, .. } if object == "a" && other == "b"),
    );
    check(|s| s.agent.x = 2.0, |e| matches!(e, SceneError::AgentInCollision { obstacle } if obstacle == "a"));
    check(|s| s.agent.x = 0.2, |e| matches!(e, SceneError::AgentInCollision { obstacle } if obstacle == "wall 3"));
    check(|s| s.agent.x = -3.0, |e| matches!(e, SceneError::AgentOutsideRoom));
}

#[test]
fn a_scene_already_solved_is_rejected_but_can_seed_backward_construction() {
    let solve = |s: &mut Scene| {
        for o in &mut s.movable_objects {
            o.pose = o.target;
        }
    };
    check(solve, |e| matches!(e, SceneError::AlreadySolved));
    let mut scene = base();
    solve(&mut scene);
    CompiledScene::for_backward_construction(scene, Rules::default()).unwrap();
}

#[test]
fn rules_are_checked() {
    let rules = Rules { collision_margin: -0.01, ..Rules::default() };
    assert!(matches!(CompiledScene::new(base(), rules), Err(SceneError::InvalidRules { .. })));
    let rules = Rules { placement_iou: 1.5, ..Rules::default() };
    assert!(matches!(CompiledScene::new(base(), rules), Err(SceneError::InvalidRules { .. })));
}

#[test]
fn malformed_json_is_an_error_with_a_position() {
    let err = Scene::from_json("{\"schema\": 1}").unwrap_err();
    assert!(matches!(&err, SceneError::Json { message } if message.contains("line 1")), "{err:?}");
    // Unknown fields are refused, so typos do not pass silently.
    let mut value = serde_json::to_value(base()).unwrap();
    value["movable_objects"][0]["tagret"] = serde_json::json!({"x": 1.0, "z": 1.0, "yaw": 0.0});
    assert!(Scene::from_json(&value.to_string()).is_err());
    // A bad action code in the expert trajectory.
    let mut value = serde_json::to_value(base()).unwrap();
    value["expert_trajectory"] = serde_json::json!([0, 9]);
    let err = Scene::from_json(&value.to_string()).unwrap_err();
    assert!(err.to_string().contains("unknown action code 9"), "{err}");
    // A bad heading.
    let mut value = serde_json::to_value(base()).unwrap();
    value["agent"]["heading"] = serde_json::json!(16);
    assert!(Scene::from_json(&value.to_string()).is_err());
}

#[test]
fn json_round_trips() {
    let scene = base();
    assert_eq!(Scene::from_json(&scene.to_json_pretty()).unwrap(), scene);
    let example = include_str!("../../examples/scenes/bedroom.json");
    let parsed = Scene::from_json(example).unwrap();
    assert_eq!(Scene::from_json(&parsed.to_json_pretty()).unwrap(), parsed);
}

/// Values that break naive code.
fn nasty() -> impl Strategy<Value = f64> {
    prop_oneof![
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(-f64::INFINITY),
        Just(0.0),
        Just(-0.0),
        Just(1e300),
        Just(-1e300),
        Just(f64::MIN_POSITIVE),
        -100.0..100.0f64,
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// Any number anywhere in a scene gives a valid scene or a typed error, never a panic.
    #[test]
    fn no_input_panics(seed in any::<u64>(), field in 0usize..12, value in nasty()) {
        let mut scene = random_scene(seed);
        let last = scene.movable_objects.len() - 1;
        match field {
            0 => scene.room.floor[1][0] = value,
            1 => scene.room.wall_height = value,
            2 => scene.room.wall_thickness = value,
            3 => scene.movable_objects[last].pose.x = value,
            4 => scene.movable_objects[0].target.yaw = value,
            5 => scene.agent.x = value,
            6 => scene.movable_objects[0].shape = Shape::Parts(vec![Part::Box { half_extents: [value, 0.2, 0.2], offset: [0.0; 3], yaw: 0.0 }]),
            7 => scene.movable_objects[0].shape = Shape::Parts(vec![Part::Cylinder { radius: 0.2, half_height: value, offset: [0.0, value, 0.0], yaw: value }]),
            8 => scene.movable_objects[0].shape = Shape::Parts(vec![Part::ConvexHull { points: vec![[value, 0.0, 0.0], [0.0, value, 0.0], [0.0, 0.0, value], [0.1, 0.1, 0.1]], offset: [0.0; 3], yaw: 0.0 }]),
            9 => scene.room.openings.push(Opening { kind: OpeningKind::Window, wall: 0, offset: value, width: 1.0, bottom: 0.5, top: value }),
            10 => scene.movable_objects[0].shape = Shape::Mesh(esrp_core::Mesh { vertices: vec![[value, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.3], [0.2, 0.2, value]], triangles: vec![[0, 1, 2], [0, 2, 3], [1, 3, 2], [0, 3, 1]] }),
            _ => scene.room.floor.push([value, value]),
        }
        let _ = CompiledScene::new(scene, Rules::default());
    }

    /// Extreme numbers the validation lets through (up to its bounds) never panic an episode:
    /// the scene compiles or is refused, and its episode steps, resets and steps again, each
    /// call answering a result (the collision library's failures are errors, never panics).
    #[test]
    fn extreme_scenes_never_panic_an_episode(
        seed in any::<u64>(),
        field in 0usize..7,
        value in prop_oneof![Just(MAX_SCENE_NUMBER), Just(-MAX_SCENE_NUMBER), Just(1e-9), Just(250.0), Just(-0.0), -MAX_SCENE_NUMBER..MAX_SCENE_NUMBER],
        actions in proptest::collection::vec(0i64..6, 1..40),
    ) {
        let mut scene = random_scene(seed);
        match field {
            0 => if let Some(fixed) = scene.fixed_objects.first_mut() {
                fixed.shape = Shape::Parts(vec![Part::Box { half_extents: [value.abs(), 0.4, 0.4], offset: [0.0; 3], yaw: 0.0 }]);
            },
            1 => scene.movable_objects[0].shape = Shape::Parts(vec![Part::Box { half_extents: [0.2, value.abs(), 0.2], offset: [0.0; 3], yaw: 0.0 }]),
            2 => scene.movable_objects[0].target.x = value,
            3 => scene.movable_objects[0].pose.yaw = value,
            4 => scene.agent.z = value,
            5 => scene.room.wall_height = value,
            _ => scene.movable_objects[0].shape = Shape::Parts(vec![Part::Cylinder { radius: value.abs(), half_height: 0.3, offset: [0.0, value, 0.0], yaw: value }]),
        }
        let Ok(compiled) = CompiledScene::new(scene, Rules::default()) else { return Ok(()) };
        let Ok(mut episode) = esrp_core::Episode::new(std::sync::Arc::new(compiled), Default::default()) else { return Ok(()) };
        for (i, &code) in actions.iter().enumerate() {
            if i == actions.len() / 2 {
                episode.reset();
            }
            if episode.step(esrp_core::Action::from_code(code).unwrap()).is_err() && !episode.is_over() {
                prop_assert!(episode.failure().is_some(), "a step fails only on a finished or failed episode");
            }
        }
    }

    /// Arbitrary text never panics the parser.
    #[test]
    fn arbitrary_json_never_panics(text in ".{0,200}") {
        let _ = Scene::from_json(&text);
    }

    #[test]
    fn random_scenes_are_valid(seed in any::<u64>()) {
        let scene = random_scene(seed);
        if let Err(e) = CompiledScene::new(scene, Rules::default()) {
            return Err(TestCaseError::fail(format!("seed {seed}: {e}")));
        }
    }
}

#[test]
fn scenes_beyond_the_size_bounds_are_refused_before_any_geometry() {
    use esrp_core::{MAX_FIXED_OBJECTS, MAX_FLOOR_VERTICES, MAX_PARTS};
    let too_large =
        |what: &'static str| move |e: &SceneError| matches!(e, SceneError::TooLarge { what: w, .. } if *w == what);
    // A floor of many vertices (a circle): refused by count, not checked pair by pair.
    check(
        |s| {
            let n = MAX_FLOOR_VERTICES + 1;
            s.room.floor = (0..n)
                .map(|i| {
                    let a = i as f64 / n as f64 * std::f64::consts::TAU;
                    [4.0 * a.cos(), 4.0 * a.sin()]
                })
                .collect();
        },
        too_large("floor vertices"),
    );
    check(
        |s| {
            let extra = s.fixed_objects[0].clone();
            s.fixed_objects = (0..=MAX_FIXED_OBJECTS)
                .map(|i| {
                    let mut o = extra.clone();
                    o.id = format!("fixed-{i}");
                    o
                })
                .collect();
        },
        too_large("fixed objects"),
    );
    check(
        |s| {
            let part = esrp_core::Part::Box { half_extents: [0.01, 0.01, 0.01], offset: [0.0; 3], yaw: 0.0 };
            s.fixed_objects[0].shape = Shape::Parts(vec![part; MAX_PARTS + 1]);
        },
        too_large("convex parts"),
    );
}

#[test]
fn reward_weights_beyond_the_bound_are_refused() {
    use esrp_core::{Episode, EpisodeConfig, EpisodeError, MAX_REWARD_WEIGHT, RewardWeights};
    let scene = std::sync::Arc::new(CompiledScene::new(base(), Rules::default()).unwrap());
    for living in [MAX_REWARD_WEIGHT * 10.0, -1e308, f64::INFINITY, f64::NAN] {
        let config =
            EpisodeConfig { reward: RewardWeights { living, ..RewardWeights::default() }, ..EpisodeConfig::default() };
        let error = Episode::new(scene.clone(), config).err();
        assert!(matches!(error, Some(EpisodeError::InvalidConfig { .. })), "{living}: {error:?}");
    }
    let config = EpisodeConfig {
        reward: RewardWeights { living: -MAX_REWARD_WEIGHT, ..RewardWeights::default() },
        ..EpisodeConfig::default()
    };
    assert!(Episode::new(scene, config).is_ok());
}
