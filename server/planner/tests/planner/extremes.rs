//! Property: the planner answers a plan or a typed error, never a panic, on scenes with extreme
//! numbers the validation lets through (up to its bounds), as a client's inline scene may have.

use std::sync::Arc;

use esrp_core::{CompiledScene, Episode, EpisodeConfig, MAX_SCENE_NUMBER, Part, Rules, Shape};
use esrp_planner::{PlanOptions, plan};
use proptest::prelude::*;

use crate::fixtures::bench_scene;

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    #[test]
    fn extreme_scenes_get_a_plan_or_an_error(
        index in 0usize..40,
        field in 0usize..5,
        value in prop_oneof![Just(MAX_SCENE_NUMBER), Just(-MAX_SCENE_NUMBER), Just(1e-9), Just(250.0), -MAX_SCENE_NUMBER..MAX_SCENE_NUMBER],
    ) {
        let mut scene = bench_scene(index);
        match field {
            0 => scene.movable_objects[0].shape = Shape::Parts(vec![Part::Box { half_extents: [0.2, value.abs(), 0.2], offset: [0.0; 3], yaw: 0.0 }]),
            1 => scene.movable_objects[0].target.x = value,
            2 => scene.movable_objects[0].target.yaw = value,
            3 => scene.room.wall_height = value,
            _ => scene.movable_objects[0].shape = Shape::Parts(vec![Part::Cylinder { radius: value.abs().min(0.3), half_height: 0.3, offset: [0.0, value, 0.0], yaw: value }]),
        }
        let Ok(compiled) = CompiledScene::new(scene, Rules::default()) else { return Ok(()) };
        let Ok(episode) = Episode::new(Arc::new(compiled), EpisodeConfig::default()) else { return Ok(()) };
        let options = PlanOptions { max_nodes: 2_000, ..PlanOptions::default() };
        let _ = plan(&episode, &options);
    }
}
