//! Scenes for the tests: benchmark scenes by index, and a small hand-made room.

use std::sync::Arc;

use esrp_core::{
    Action, AgentStart, CompiledScene, Difficulty, Episode, EpisodeConfig, EpisodeStatus, Heading, MovableCategory,
    MovableObject, ObjectPose, Part, Room, SCENE_SCHEMA, Scene, Shape, Split,
};
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED};

/// Scene `index` of esrp-bench-v1 as generated (the scenes these tests were written against).
pub fn bench_scene(index: usize) -> Scene {
    match Benchmark::new(BenchVersion::V1, DEFAULT_SEED).generate(index) {
        Ok(generated) => generated.scene,
        Err(error) => panic!("scene {index} failed to generate: {error:?}"),
    }
}

/// A fresh episode of `scene` with the default configuration.
pub fn episode_of(scene: Scene) -> Episode {
    let compiled = CompiledScene::shared(scene).expect("a valid scene");
    Episode::new(compiled, EpisodeConfig::default()).expect("a valid configuration")
}

/// A fresh episode of benchmark scene `index`.
pub fn bench_episode(index: usize) -> Episode {
    episode_of(bench_scene(index))
}

/// Steps `actions` on a clone of `episode` and checks the plan's contract: every action is
/// accepted (no collision, no no-op) and the episode ends in success, within its horizon.
pub fn assert_replays_to_success(episode: &Episode, actions: &[Action]) {
    let mut replay = episode.clone();
    let steps_left = episode.horizon() - episode.steps();
    assert!(actions.len() <= steps_left as usize, "{} actions for {steps_left} steps left", actions.len());
    for (i, &action) in actions.iter().enumerate() {
        let outcome =
            replay.step(action).unwrap_or_else(|e| panic!("action {i} ({action:?}) on an ended episode: {e}"));
        assert!(outcome.accepted, "action {i} ({action:?}) was not accepted: {outcome:?}");
    }
    assert_eq!(replay.status(), EpisodeStatus::Succeeded, "the plan does not end in success");
}

/// A stool: one box, 0.4 m square, 0.45 m tall.
fn stool(id: &str, pose: ObjectPose, target: ObjectPose) -> MovableObject {
    MovableObject {
        id: id.into(),
        category: MovableCategory::PierStool,
        model: "stool_test".into(),
        shape: Shape::Parts(vec![Part::Box { half_extents: [0.2, 0.225, 0.2], offset: [0.0, 0.225, 0.0], yaw: 0.0 }]),
        pose,
        target,
    }
}

/// A 5 m × 5 m room with two stools. Stool `b`'s target stands against the east wall; stool
/// `a` is placed (IoU 0.38 with its target, just west of `b`'s) but pushed 0.18 m east, onto
/// `b`'s target, so `b` cannot be placed until `a` moves.
pub fn placed_blocker_scene() -> Scene {
    let at = |x: f64, z: f64| ObjectPose::new(x, z, 0.0);
    Scene {
        schema: SCENE_SCHEMA.into(),
        id: "test/placed-blocker".into(),
        room_type: "LivingRoom".into(),
        difficulty: Difficulty::Medium,
        split: Split::Test,
        room: Room {
            floor: vec![[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]],
            wall_height: 2.6,
            wall_thickness: 0.12,
            openings: Vec::new(),
        },
        fixed_objects: Vec::new(),
        movable_objects: vec![
            stool("stool-a", at(4.53, 2.5), at(4.35, 2.5)),
            stool("stool-b", at(2.0, 1.0), at(4.78, 2.5)),
        ],
        agent: AgentStart { x: 1.0, z: 1.0, heading: Heading::wrapping(0) },
        horizon: 300,
        expert_trajectory: Vec::new(),
    }
}

/// Shares a compiled scene.
pub fn compiled(scene: Scene) -> Arc<CompiledScene> {
    CompiledScene::shared(scene).expect("a valid scene")
}
