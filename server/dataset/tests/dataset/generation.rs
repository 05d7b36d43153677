//! Generation: determinism, curation rules, expert replay, benchmark structure.

use esrp_core::{Action, CompiledScene, Episode, EpisodeConfig, Rules, footprint_iou};
use esrp_dataset::benchmark::OBJECT_COUNT_MIX;
use esrp_dataset::catalogue::by_name;
use esrp_dataset::layout::ROOM_TYPES;
use esrp_dataset::{BENCH_SCENES, BenchVersion, Benchmark, DEFAULT_SEED, validate_by_replay};

/// A spread of indices with every object count (1 to 6) among them.
fn sample_indices(bench: &Benchmark) -> Vec<usize> {
    let mut chosen = Vec::new();
    for objects in 1..=6 {
        let found = (0..bench.len()).filter(|&i| bench.object_count(i) == objects).take(2);
        chosen.extend(found);
    }
    chosen
}

#[test]
fn the_benchmark_has_the_documented_structure() {
    let bench = Benchmark::new(BenchVersion::default(), DEFAULT_SEED);
    assert_eq!(bench.len(), BENCH_SCENES);
    for (room_type, count) in ROOM_TYPES {
        assert_eq!((0..bench.len()).filter(|&i| bench.room_type(i) == room_type).count(), count, "{room_type}");
    }
    for (objects, count) in OBJECT_COUNT_MIX {
        assert_eq!((0..bench.len()).filter(|&i| bench.object_count(i) == objects).count(), count, "{objects} objects");
    }
    // Another seed shuffles differently but keeps the counts.
    let other = Benchmark::new(BenchVersion::default(), 1);
    assert!((0..50).any(|i| other.room_type(i) != bench.room_type(i)));
}

#[test]
fn generated_scenes_follow_every_curation_rule_and_replay() {
    let bench = Benchmark::new(BenchVersion::default(), DEFAULT_SEED);
    for index in sample_indices(&bench) {
        let scene = bench.generate(index).unwrap_or_else(|e| panic!("{e}")).scene;
        let id = &scene.id;
        assert_eq!(id, &bench.scene_id(index));
        assert_eq!(scene.room_type, bench.room_type(index));
        assert_eq!(scene.movable_objects.len(), bench.object_count(index), "{id}");
        assert_eq!(Some(scene.difficulty), esrp_core::Difficulty::for_object_count(scene.movable_objects.len()));
        assert_eq!(scene.split, bench.split(index));
        // Movable pieces are carryable catalogue models; the room stays within its triangle budget.
        let mut triangles = 0;
        for o in &scene.movable_objects {
            let model = by_name(&o.model).unwrap_or_else(|| panic!("{id}: unknown model {}", o.model));
            assert_eq!(model.movable, Some(o.category), "{id}: {}", o.model);
            assert!(model.depth().max(model.width()) <= 1.2 && model.size[1] <= 1.3);
            triangles += model.triangle_estimate();
        }
        for o in &scene.fixed_objects {
            triangles += by_name(&o.model).map_or(0, |m| m.triangle_estimate());
        }
        assert!(triangles <= esrp_dataset::layout::TRIANGLE_BUDGET, "{id}: {triangles} triangles");
        // Nothing starts placed: every object is clearly away from its target.
        let compiled = std::sync::Arc::new(CompiledScene::new(scene.clone(), Rules::default()).unwrap());
        for (i, o) in scene.movable_objects.iter().enumerate() {
            let iou = footprint_iou(&compiled.movable_footprint(i, &o.pose), &compiled.movable_footprint(i, &o.target));
            assert!(iou <= 0.05, "{id}: object {i} starts with IoU {iou}");
        }
        // The horizon rule and a successful expert.
        assert_eq!(scene.horizon, esrp_dataset::backward::horizon_for(scene.expert_trajectory.len()));
        assert!(scene.expert_trajectory.iter().filter(|a| **a == Action::Fetch).count() >= scene.movable_objects.len());
        let mut episode = Episode::new(compiled, EpisodeConfig::default()).unwrap();
        for &a in &scene.expert_trajectory {
            episode.step(a).unwrap();
        }
        let m = episode.metrics();
        assert!(m.success, "{id}: expert fails: {m:?}");
        assert!(m.steps as usize == scene.expert_trajectory.len());
        validate_by_replay(&scene).unwrap();
    }
}

#[test]
fn generation_is_deterministic_and_a_scene_alone_equals_the_same_scene_in_a_run() {
    for version in BenchVersion::ALL {
        let bench = Benchmark::new(version, DEFAULT_SEED);
        for index in [0, 7, 33] {
            let a = bench.generate(index).unwrap().scene.to_json_pretty();
            let b = Benchmark::new(version, DEFAULT_SEED).generate(index).unwrap().scene.to_json_pretty();
            assert_eq!(a, b, "scene {index}");
        }
        // A different seed gives different scenes.
        let other = Benchmark::new(version, 5).generate(0).unwrap().scene;
        assert_ne!(other.to_json_pretty(), bench.generate(0).unwrap().scene.to_json_pretty());
        assert_eq!(other.id, format!("{version}-s5/00000"));
    }
}

#[test]
fn a_broken_expert_is_caught_by_the_replay_check() {
    let mut scene = Benchmark::new(BenchVersion::default(), DEFAULT_SEED).generate(3).unwrap().scene;
    scene.expert_trajectory.truncate(scene.expert_trajectory.len() - 1);
    assert!(validate_by_replay(&scene).is_err());
}
