//! `cargo bench -p esrp-core --bench step`: the cost of one motion action on a furnished room
//! with 6 movable objects and 18 fixed pieces, with and without a held object.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use esrp_core::{
    Action, AgentStart, CompiledScene, Difficulty, Episode, EpisodeConfig, FixedObject, Heading, MovableCategory,
    MovableObject, ObjectPose, Part, Room, SCENE_SCHEMA, Scene, Shape, Split,
};

fn block(hx: f64, hz: f64, height: f64, y0: f64) -> Part {
    Part::Box { half_extents: [hx, height / 2.0, hz], offset: [0.0, y0 + height / 2.0, 0.0], yaw: 0.0 }
}

/// A table: top and four legs.
fn table(hx: f64, hz: f64) -> Vec<Part> {
    let mut parts = vec![block(hx, hz, 0.04, 0.7)];
    for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
        parts.push(Part::Cylinder {
            radius: 0.03,
            half_height: 0.35,
            offset: [sx * (hx - 0.05), 0.35, sz * (hz - 0.05)],
            yaw: 0.0,
        });
    }
    parts
}

/// A chair: seat, back and four legs.
fn chair() -> Vec<Part> {
    let mut parts = vec![block(0.22, 0.22, 0.05, 0.42), block(0.03, 0.22, 0.45, 0.47)];
    if let Part::Box { offset, .. } = &mut parts[1] {
        offset[0] = -0.19;
    }
    for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
        parts.push(Part::Box { half_extents: [0.02, 0.21, 0.02], offset: [sx * 0.19, 0.21, sz * 0.19], yaw: 0.0 });
    }
    parts
}

fn bench_scene() -> Scene {
    let mut fixed = Vec::new();
    let mut add = |id: String, parts: Vec<Part>, x: f64, z: f64| {
        fixed.push(FixedObject {
            id,
            category: "furniture".into(),
            model: String::new(),
            shape: Shape::Parts(parts),
            pose: ObjectPose::new(x, z, 0.0),
        })
    };
    // Cabinets along the top and bottom walls, tables in the middle row.
    for i in 0..7 {
        add(format!("cabinet-top-{i}"), vec![block(0.3, 0.25, 0.9, 0.0)], 0.6 + 1.1 * f64::from(i), 0.3);
        add(format!("cabinet-bottom-{i}"), vec![block(0.3, 0.25, 0.9, 0.0)], 0.6 + 1.1 * f64::from(i), 5.7);
    }
    for i in 0..4 {
        add(format!("table-{i}"), table(0.4, 0.3), 1.0 + 2.0 * f64::from(i), 3.9);
    }
    let movable = |i: usize, parts: Vec<Part>, x: f64, z: f64| MovableObject {
        id: format!("movable-{i}"),
        category: MovableCategory::Chair,
        model: String::new(),
        shape: Shape::Parts(parts),
        pose: ObjectPose::new(x, z, 0.0),
        target: ObjectPose::new(x, z + 1.2, 0.0),
    };
    let movable_objects = (0..6)
        .map(|i| {
            let parts = if i % 2 == 0 { chair() } else { vec![block(0.2, 0.2, 0.6, 0.0)] };
            movable(i, parts, 1.5 + 1.0 * i as f64, 1.3)
        })
        .collect();
    Scene {
        schema: SCENE_SCHEMA.into(),
        id: "bench/furnished".into(),
        room_type: "LivingDiningRoom".into(),
        difficulty: Difficulty::Hard,
        split: Split::Test,
        room: Room {
            floor: vec![[0.0, 0.0], [8.0, 0.0], [8.0, 6.0], [0.0, 6.0]],
            wall_height: 2.6,
            wall_thickness: 0.12,
            openings: Vec::new(),
        },
        fixed_objects: fixed,
        movable_objects,
        agent: AgentStart { x: 4.0, z: 2.45, heading: Heading::new(4).expect("valid") },
        horizon: 200,
        expert_trajectory: Vec::new(),
    }
}

fn bench_step(c: &mut Criterion) {
    let scene = Arc::new(CompiledScene::new(bench_scene(), Default::default()).expect("bench scene is valid"));
    let config = EpisodeConfig { horizon: Some(u32::MAX), ..Default::default() };
    let free = Episode::new(scene.clone(), config).expect("episode");
    // Facing −z between two objects at equal distance: fetch takes the first, a chair.
    let mut holding = free.clone();
    let fetched = holding.step(Action::Fetch).expect("running");
    assert!(fetched.fetched.is_some(), "the bench agent must start within reach of an object");

    let mut group = c.benchmark_group("step");
    for (name, episode) in [("free", &free), ("holding", &holding)] {
        for (motion, pair) in
            [("move", [Action::MoveForward, Action::MoveBackward]), ("turn", [Action::TurnLeft, Action::TurnRight])]
        {
            let mut e = episode.clone();
            for a in pair {
                assert!(e.step(a).expect("running").accepted, "{name}/{motion}: {a:?} must be accepted");
            }
            let mut flip = false;
            group.bench_function(format!("{name}/{motion}"), |b| {
                b.iter(|| {
                    flip = !flip;
                    black_box(e.step(if flip { pair[0] } else { pair[1] }).expect("running"))
                })
            });
        }
    }
    // Rejected motions: the state does not change, so every iteration repeats the same check.
    let mut blocked = free.clone();
    let backed_into_a_cabinet = (0..16).any(|_| blocked.step(Action::MoveBackward).expect("running").collided());
    assert!(backed_into_a_cabinet, "backing up must meet the cabinets");
    group.bench_function("free/move-rejected", |b| {
        b.iter(|| black_box(blocked.step(Action::MoveBackward).expect("running")))
    });
    // Turn the held chair left until its arc meets the neighbouring object.
    let mut blocked = holding.clone();
    let mut found = false;
    for _ in 0..16 {
        if blocked.step(Action::TurnLeft).expect("running").collided() {
            found = true;
            break;
        }
    }
    assert!(found, "the held chair must meet an obstacle within a full turn");
    group.bench_function("holding/turn-rejected", |b| {
        b.iter(|| black_box(blocked.step(Action::TurnLeft).expect("running")))
    });
    // A random walk in the furnished room (fetches and releases included): the cost of a step in
    // a realistic mix of free, carried, rejected and near-obstacle motions.
    let mut seed = 0x2545_F491_4F6C_DD1Du64;
    let walk: Vec<Action> = (0..4096)
        .map(|_| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            match seed % 12 {
                0..=3 => Action::MoveForward,
                4 | 5 => Action::MoveBackward,
                6 | 7 => Action::TurnLeft,
                8 | 9 => Action::TurnRight,
                10 => Action::Fetch,
                _ => Action::Release,
            }
        })
        .collect();
    let mut walker = free.clone();
    let mut next = 0;
    group.bench_function("random-walk", |b| {
        b.iter(|| {
            if walker.is_over() {
                walker.reset();
            }
            next = (next + 1) % walk.len();
            black_box(walker.step(walk[next]).expect("running"))
        })
    });
    group.finish();
}

criterion_group!(benches, bench_step);
criterion_main!(benches);
