//! Small hand-made scenes for the tests.

use std::sync::Arc;

use esrp_core::{
    Action, AgentStart, CompiledScene, Difficulty, Episode, EpisodeConfig, FixedObject, Heading, MovableCategory,
    MovableObject, ObjectPose, Part, Room, SCENE_SCHEMA, Scene, Shape, Split,
};

/// A box part standing on the floor.
pub fn box_part(half_x: f64, half_z: f64, height: f64) -> Part {
    Part::Box { half_extents: [half_x, height / 2.0, half_z], offset: [0.0, height / 2.0, 0.0], yaw: 0.0 }
}

/// A vertical cylinder standing on the floor.
pub fn cylinder_part(radius: f64, height: f64) -> Part {
    Part::Cylinder { radius, half_height: height / 2.0, offset: [0.0, height / 2.0, 0.0], yaw: 0.0 }
}

/// Builds scenes in a rectangular room `[0, width] × [0, depth]`.
#[derive(Clone)]
pub struct SceneBuilder {
    pub scene: Scene,
}

impl SceneBuilder {
    pub fn room(width: f64, depth: f64) -> Self {
        Self {
            scene: Scene {
                schema: SCENE_SCHEMA.into(),
                id: "test/scene".into(),
                room_type: "LivingRoom".into(),
                difficulty: Difficulty::Easy,
                split: Split::Test,
                room: Room {
                    floor: vec![[0.0, 0.0], [width, 0.0], [width, depth], [0.0, depth]],
                    wall_height: 2.6,
                    wall_thickness: 0.12,
                    openings: Vec::new(),
                },
                fixed_objects: Vec::new(),
                movable_objects: Vec::new(),
                agent: AgentStart { x: width / 2.0, z: depth / 2.0, heading: Heading::new(0).unwrap() },
                horizon: 200,
                expert_trajectory: Vec::new(),
            },
        }
    }

    pub fn agent(mut self, x: f64, z: f64, heading: u8) -> Self {
        self.scene.agent = AgentStart { x, z, heading: Heading::new(heading).unwrap() };
        self
    }

    pub fn horizon(mut self, horizon: u32) -> Self {
        self.scene.horizon = horizon;
        self
    }

    pub fn fixed(mut self, id: &str, parts: Vec<Part>, x: f64, z: f64, yaw: f64) -> Self {
        self.scene.fixed_objects.push(FixedObject {
            id: id.into(),
            category: "table".into(),
            model: String::new(),
            shape: Shape::Parts(parts),
            pose: ObjectPose::new(x, z, yaw),
        });
        self
    }

    pub fn movable(mut self, id: &str, parts: Vec<Part>, pose: ObjectPose, target: ObjectPose) -> Self {
        self.scene.movable_objects.push(MovableObject {
            id: id.into(),
            category: MovableCategory::Others,
            model: String::new(),
            shape: Shape::Parts(parts),
            pose,
            target,
        });
        self
    }

    /// The scene, with its difficulty set from its object count.
    pub fn build(mut self) -> Scene {
        if let Some(d) = Difficulty::for_object_count(self.scene.movable_objects.len()) {
            self.scene.difficulty = d;
        }
        self.scene
    }

    pub fn compile(self) -> Arc<CompiledScene> {
        let scene = self.build();
        match CompiledScene::shared(scene) {
            Ok(c) => c,
            Err(e) => panic!("fixture scene is invalid: {e}"),
        }
    }

    pub fn episode(self) -> Episode {
        Episode::new(self.compile(), EpisodeConfig::default()).unwrap()
    }
}

/// A pose shorthand.
pub fn pose(x: f64, z: f64, yaw: f64) -> ObjectPose {
    ObjectPose::new(x, z, yaw)
}

/// A 0.4 × 0.4 × 0.5 m box: a small cabinet.
pub fn small_box() -> Vec<Part> {
    vec![box_part(0.2, 0.2, 0.5)]
}

/// A deterministic SplitMix64 generator for building random scenes from a proptest seed.
pub struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[lo, hi)`.
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }

    pub fn below(&mut self, n: u64) -> u64 {
        self.next_u64() % n
    }
}

/// A random movable or fixed shape of one to three parts, and its bounding radius on the plan.
fn random_shape(rng: &mut SplitMix) -> (Vec<Part>, f64) {
    match rng.below(4) {
        0 => {
            let (hx, hz) = (rng.range(0.1, 0.35), rng.range(0.1, 0.35));
            (vec![box_part(hx, hz, rng.range(0.3, 1.2))], hx.hypot(hz))
        }
        1 => {
            let r = rng.range(0.1, 0.3);
            (vec![cylinder_part(r, rng.range(0.3, 1.0))], r)
        }
        2 => {
            // A chair-like union: seat, back and a leg.
            let s = rng.range(0.2, 0.3);
            let parts = vec![
                Part::Box { half_extents: [s, 0.05, s], offset: [0.0, 0.45, 0.0], yaw: 0.0 },
                Part::Box { half_extents: [0.04, 0.3, s], offset: [-s + 0.04, 0.8, 0.0], yaw: 0.0 },
                Part::Cylinder { radius: 0.04, half_height: 0.2, offset: [0.0, 0.2, 0.0], yaw: 0.0 },
            ];
            (parts, s * std::f64::consts::SQRT_2)
        }
        _ => {
            let r = rng.range(0.15, 0.3);
            let h = rng.range(0.3, 1.0);
            let points = vec![[-r, 0.0, -r], [r, 0.0, -r], [0.0, 0.0, r], [0.0, h, 0.0], [r * 0.5, h * 0.5, r * 0.5]];
            (vec![Part::ConvexHull { points, offset: [0.0, 0.0, 0.0], yaw: rng.range(0.0, 6.3) }], r * 1.5)
        }
    }
}

/// A random valid scene: a room of 4–7 m with some fixed pieces, 1–6 movable objects and the
/// agent, all kept apart by their bounding circles so that the scene validates.
pub fn random_scene(seed: u64) -> Scene {
    let mut rng = SplitMix(seed);
    let (width, depth) = (rng.range(4.0, 7.0), rng.range(4.0, 7.0));
    let mut b = SceneBuilder::room(width, depth);
    // Circles already used in the initial (index 0) and target (index 1) layouts.
    let mut used: [Vec<(f64, f64, f64)>; 2] = [Vec::new(), Vec::new()];
    let clear = |used: &Vec<(f64, f64, f64)>, x: f64, z: f64, r: f64| {
        used.iter().all(|&(ux, uz, ur)| (ux - x).hypot(uz - z) > ur + r + 0.05)
    };
    let place = |rng: &mut SplitMix, r: f64| {
        let margin = r + 0.08;
        (rng.range(margin, width - margin), rng.range(margin, depth - margin))
    };
    let (ax, az) = place(&mut rng, 0.3);
    b = b.agent(ax, az, rng.below(16) as u8);
    used[0].push((ax, az, 0.3));
    for i in 0..rng.below(4) {
        let (parts, r) = random_shape(&mut rng);
        for _ in 0..20 {
            let (x, z) = place(&mut rng, r);
            if clear(&used[0], x, z, r) && clear(&used[1], x, z, r) {
                used[0].push((x, z, r));
                used[1].push((x, z, r));
                b = b.fixed(&format!("fixed-{i}"), parts, x, z, rng.range(0.0, 6.3));
                break;
            }
        }
    }
    let wanted = 1 + rng.below(6);
    let mut count = 0;
    for _ in 0..400 {
        if count == wanted {
            break;
        }
        let (parts, r) = random_shape(&mut rng);
        let (x, z) = place(&mut rng, r);
        let (tx, tz) = place(&mut rng, r);
        if clear(&used[0], x, z, r) && clear(&used[1], tx, tz, r) && (x - tx).hypot(z - tz) > 2.0 * r + 0.1 {
            used[0].push((x, z, r));
            used[1].push((tx, tz, r));
            b = b.movable(
                &format!("movable-{count}"),
                parts,
                pose(x, z, rng.range(0.0, 6.3)),
                pose(tx, tz, rng.range(0.0, 6.3)),
            );
            count += 1;
        }
    }
    b.build()
}

/// Random actions biased towards motion, with fetches and releases mixed in.
pub fn random_actions(seed: u64, count: usize) -> Vec<Action> {
    let mut rng = SplitMix(seed ^ 0xA5A5_5A5A);
    (0..count)
        .map(|_| match rng.below(12) {
            0..=3 => Action::MoveForward,
            4 | 5 => Action::MoveBackward,
            6 | 7 => Action::TurnLeft,
            8 | 9 => Action::TurnRight,
            10 => Action::Fetch,
            _ => Action::Release,
        })
        .collect()
}
