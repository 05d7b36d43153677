//! Shared fixtures: one renderer for the whole binary, hand-made scenes, pixel helpers.

use std::sync::{Arc, OnceLock};

use esrp_core::{
    AgentStart, CompiledScene, Difficulty, EgoCamera, Episode, EpisodeConfig, FixedObject, Heading, Mesh,
    MovableCategory, MovableObject, ObjectPose, Opening, OpeningKind, Part, Room, SCENE_SCHEMA, Scene, Shape, Split,
};
use esrp_render::{BackendPreference, Renderer, RendererConfig};

/// The renderer every test shares (batches serialise on its mutex): Vulkan (lavapipe on a
/// machine without a GPU) unless `ESRP_RENDER_BACKEND` says otherwise (`gl` runs the suite on
/// OpenGL, `auto` on what the server would pick).
pub fn renderer() -> &'static Renderer {
    static RENDERER: OnceLock<Renderer> = OnceLock::new();
    let backends = backend();
    RENDERER.get_or_init(|| match Renderer::new(RendererConfig { backends, ..RendererConfig::default() }) {
        Ok(r) => {
            eprintln!("esrp-render tests on {:?}", r.adapter_info());
            r
        }
        Err(e) => panic!("esrp-render tests need a graphics adapter and found none: {e}"),
    })
}

/// The backends the tests render with (see [`renderer`]).
pub fn backend() -> BackendPreference {
    BackendPreference::from_env().unwrap_or(BackendPreference::Vulkan)
}

/// Uniform numbers in [0, 1) from `seed` (xorshift64; a non-zero seed), for scattering views.
pub fn uniform(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A box part standing on the floor.
pub fn box_part(half_x: f64, half_z: f64, height: f64) -> Part {
    Part::Box { half_extents: [half_x, height / 2.0, half_z], offset: [0.0, height / 2.0, 0.0], yaw: 0.0 }
}

/// A cylinder standing on the floor.
pub fn cylinder_part(radius: f64, height: f64) -> Part {
    Part::Cylinder { radius, half_height: height / 2.0, offset: [0.0, height / 2.0, 0.0], yaw: 0.0 }
}

pub fn pose(x: f64, z: f64, yaw: f64) -> ObjectPose {
    ObjectPose::new(x, z, yaw)
}

/// A scene in a room with the given floor polygon.
pub fn scene(id: &str, floor: Vec<[f64; 2]>, agent: (f64, f64, u8)) -> Scene {
    Scene {
        schema: SCENE_SCHEMA.into(),
        id: id.into(),
        room_type: "LivingRoom".into(),
        difficulty: Difficulty::Easy,
        split: Split::Test,
        room: Room { floor, wall_height: 2.6, wall_thickness: 0.12, openings: Vec::new() },
        fixed_objects: Vec::new(),
        movable_objects: Vec::new(),
        agent: AgentStart { x: agent.0, z: agent.1, heading: Heading::new(agent.2).unwrap() },
        horizon: 200,
        expert_trajectory: Vec::new(),
    }
}

pub fn movable(
    id: &str,
    category: MovableCategory,
    parts: Vec<Part>,
    pose: ObjectPose,
    target: ObjectPose,
) -> MovableObject {
    MovableObject { id: id.into(), category, model: String::new(), shape: Shape::Parts(parts), pose, target }
}

pub fn fixed(id: &str, shape: Shape, pose: ObjectPose) -> FixedObject {
    FixedObject { id: id.into(), category: "table".into(), model: String::new(), shape, pose }
}

pub fn compile(mut scene: Scene) -> Arc<CompiledScene> {
    if let Some(d) = Difficulty::for_object_count(scene.movable_objects.len()) {
        scene.difficulty = d;
    }
    match CompiledScene::shared(scene) {
        Ok(c) => c,
        Err(e) => panic!("fixture scene is invalid: {e}"),
    }
}

/// The example bedroom of esrp-core.
pub fn bedroom() -> Arc<CompiledScene> {
    let text = include_str!("../../../core/examples/scenes/bedroom.json");
    compile(Scene::from_json(text).unwrap())
}

/// An empty 6 × 4 m room with one 0.4 m cube (a cabinet) at `(x, z)`, target elsewhere.
pub fn one_box_room(x: f64, z: f64) -> Arc<CompiledScene> {
    let mut s = scene("test/one-box", vec![[0.0, 0.0], [6.0, 0.0], [6.0, 4.0], [0.0, 4.0]], (1.0, 2.0, 0));
    s.movable_objects.push(movable(
        "box",
        MovableCategory::CabinetShelfDesk,
        vec![box_part(0.2, 0.2, 0.4)],
        pose(x, z, 0.0),
        pose(0.6, 0.6, 0.0),
    ));
    compile(s)
}

/// An L-shaped room with a door and a window, fixed furniture of every shape kind (box,
/// cylinder, convex hull, mesh) and one movable object of every category.
pub fn showcase() -> Arc<CompiledScene> {
    let mut s = scene(
        "test/showcase",
        vec![[0.0, 0.0], [6.0, 0.0], [6.0, 3.0], [3.0, 3.0], [3.0, 5.5], [0.0, 5.5]],
        (1.5, 4.5, 3),
    );
    s.room.openings = vec![
        Opening { kind: OpeningKind::Door, wall: 0, offset: 4.0, width: 0.9, bottom: 0.0, top: 2.05 },
        Opening { kind: OpeningKind::Window, wall: 1, offset: 0.8, width: 1.4, bottom: 0.8, top: 2.0 },
    ];
    let hull = Part::ConvexHull {
        points: vec![[-0.3, 0.0, -0.3], [0.3, 0.0, -0.3], [0.3, 0.0, 0.3], [-0.3, 0.0, 0.3], [0.0, 1.2, 0.0]],
        offset: [0.0; 3],
        yaw: 0.3,
    };
    // A wedge (triangular prism) as a mesh, counter-clockwise seen from outside.
    let wedge = Mesh {
        vertices: vec![
            [-0.4, 0.0, -0.3],
            [0.4, 0.0, -0.3],
            [-0.4, 0.8, -0.3],
            [-0.4, 0.0, 0.3],
            [0.4, 0.0, 0.3],
            [-0.4, 0.8, 0.3],
        ],
        triangles: vec![[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [0, 3, 5], [0, 5, 2], [1, 2, 5], [1, 5, 4]],
    };
    s.fixed_objects = vec![
        fixed("table", Shape::Parts(vec![box_part(0.6, 0.4, 0.75)]), pose(4.8, 1.0, 0.0)),
        fixed("pillar", Shape::Parts(vec![cylinder_part(0.25, 2.6)]), pose(2.6, 2.6, 0.0)),
        fixed("tent", Shape::Parts(vec![hull]), pose(0.5, 0.5, 0.0)),
        fixed("wedge", Shape::Mesh(wedge), pose(5.4, 2.4, 0.0)),
    ];
    s.movable_objects = vec![
        movable(
            "cabinet",
            MovableCategory::CabinetShelfDesk,
            vec![box_part(0.25, 0.2, 0.9)],
            pose(1.0, 2.2, 0.0),
            pose(1.0, 1.4, 0.0),
        ),
        movable(
            "chair",
            MovableCategory::Chair,
            vec![
                box_part(0.22, 0.22, 0.45),
                Part::Box { half_extents: [0.04, 0.25, 0.22], offset: [-0.18, 0.7, 0.0], yaw: 0.0 },
            ],
            pose(2.0, 1.2, 0.8),
            pose(3.5, 2.0, 0.0),
        ),
        movable(
            "sofa",
            MovableCategory::Sofa,
            vec![box_part(0.45, 0.3, 0.5)],
            pose(1.6, 3.4, 1.57),
            pose(0.7, 3.5, 0.0),
        ),
        movable(
            "stool",
            MovableCategory::PierStool,
            vec![cylinder_part(0.2, 0.45)],
            pose(2.3, 4.5, 0.0),
            pose(4.0, 2.2, 0.0),
        ),
        movable(
            "plant",
            MovableCategory::Others,
            vec![Part::ConvexHull {
                points: vec![
                    [-0.15, 0.0, -0.15],
                    [0.15, 0.0, -0.15],
                    [0.15, 0.0, 0.15],
                    [-0.15, 0.0, 0.15],
                    [0.0, 0.8, 0.0],
                ],
                offset: [0.0; 3],
                yaw: 0.0,
            }],
            pose(0.6, 4.9, 0.0),
            pose(2.5, 0.5, 0.0),
        ),
    ];
    compile(s)
}

/// The start egocentric camera and current poses of a scene.
pub fn start(scene: &Arc<CompiledScene>) -> (EgoCamera, Vec<ObjectPose>) {
    let episode = Episode::new(Arc::clone(scene), EpisodeConfig::default()).unwrap();
    (episode.ego_camera(), episode.object_poses().to_vec())
}

/// Target poses of a scene.
pub fn targets(scene: &CompiledScene) -> Vec<ObjectPose> {
    scene.scene().movable_objects.iter().map(|o| o.target).collect()
}

/// An egocentric camera at `(x, z)` with heading index `k` (SPEC §2 pose).
pub fn ego_at(x: f64, z: f64, heading: u8) -> EgoCamera {
    EgoCamera {
        eye: [x, 1.25, z],
        yaw: Heading::new(heading).unwrap().yaw(),
        pitch: 20f64.to_radians(),
        horizontal_fov: 90f64.to_radians(),
    }
}

/// `n` egocentric cameras scattered over the bedroom's floor (x and z in 0.6-3.6 m, any of the
/// 16 headings), drawn from [`uniform`]`(seed)`.
pub fn scattered_cameras(seed: u64, n: usize) -> Vec<EgoCamera> {
    let mut unit = uniform(seed);
    (0..n).map(|_| ego_at(0.6 + 3.0 * unit(), 0.6 + 3.0 * unit(), (unit() * 16.0) as u8)).collect()
}

/// A renderer of its own (not the shared [`renderer`]), on the tests' backend, culling or not:
/// for tests that count its work or compare two renderers.
pub fn own_renderer(cull: bool) -> Renderer {
    renderer_with(RendererConfig { cull, ..RendererConfig::default() })
}

/// A renderer of its own made with `config`, on the tests' backend (whatever `config` says).
pub fn renderer_with(config: RendererConfig) -> Renderer {
    Renderer::new(RendererConfig { backends: backend(), ..config })
        .unwrap_or_else(|e| panic!("esrp-render tests need a graphics adapter and found none: {e}"))
}

/// Pixels `(col, row)` whose segmentation id is `id`, and their centroid.
pub fn pixels_with(segmentation: &[u32], resolution: u32, id: u32) -> (usize, (f64, f64)) {
    let (mut n, mut sc, mut sr) = (0usize, 0.0, 0.0);
    for (i, &v) in segmentation.iter().enumerate() {
        if v == id {
            n += 1;
            sc += (i as u32 % resolution) as f64 + 0.5;
            sr += (i as u32 / resolution) as f64 + 0.5;
        }
    }
    (n, if n > 0 { (sc / n as f64, sr / n as f64) } else { (f64::NAN, f64::NAN) })
}
