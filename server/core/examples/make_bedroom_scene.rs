//! Builds `examples/scenes/bedroom.json` by backward construction by hand (SPEC §7): start from
//! the target layout, carry each object away with a scripted run of the simulator, and keep the
//! final poses as the initial layout and the reversed run as the expert trajectory.
//!
//! `cargo run -p esrp-core --example make_bedroom_scene > server/core/examples/scenes/bedroom.json`

use esrp_core::{
    Action, AgentStart, CompiledScene, Difficulty, Episode, EpisodeConfig, FixedObject, Heading, MovableCategory,
    MovableObject, ObjectPose, Opening, OpeningKind, Part, Room, Rules, SCENE_SCHEMA, Scene, Shape, Split,
    reverse_trajectory,
};

fn block(half_extents: [f64; 3], offset: [f64; 3]) -> Part {
    Part::Box { half_extents, offset, yaw: 0.0 }
}

fn target_scene() -> Scene {
    let fixed = |id: &str, category: &str, parts: Vec<Part>, x: f64, z: f64, yaw: f64| FixedObject {
        id: id.into(),
        category: category.into(),
        model: format!("{category}_example"),
        shape: Shape::Parts(parts),
        pose: ObjectPose::new(x, z, yaw),
    };
    let movable = |id: &str, category: MovableCategory, model: &str, parts: Vec<Part>, target: ObjectPose| {
        MovableObject { id: id.into(), category, model: model.into(), shape: Shape::Parts(parts), pose: target, target }
    };
    Scene {
        schema: SCENE_SCHEMA.into(),
        id: "example/bedroom-0".into(),
        room_type: "Bedroom".into(),
        difficulty: Difficulty::Medium,
        split: Split::Test,
        room: Room {
            floor: vec![[0.0, 0.0], [5.0, 0.0], [5.0, 4.0], [0.0, 4.0]],
            wall_height: 2.6,
            wall_thickness: 0.12,
            openings: vec![
                Opening { kind: OpeningKind::Door, wall: 0, offset: 0.5, width: 0.9, bottom: 0.0, top: 2.05 },
                Opening { kind: OpeningKind::Window, wall: 1, offset: 1.0, width: 1.2, bottom: 0.9, top: 2.1 },
            ],
        },
        fixed_objects: vec![
            fixed(
                "bed-0",
                "bed",
                vec![block([1.0, 0.25, 0.8], [0.0, 0.25, 0.0]), block([0.05, 0.5, 0.8], [0.95, 0.5, 0.0])],
                3.98,
                2.6,
                0.0,
            ),
            fixed("nightstand-0", "nightstand", vec![block([0.22, 0.27, 0.2], [0.0, 0.27, 0.0])], 4.76, 1.45, 0.0),
            fixed("wardrobe-0", "wardrobe", vec![block([0.3, 1.0, 0.6], [0.0, 1.0, 0.0])], 0.32, 3.0, 0.0),
        ],
        movable_objects: vec![
            movable(
                "armchair-0",
                MovableCategory::Sofa,
                "armchair_example",
                vec![
                    block([0.4, 0.2, 0.4], [0.0, 0.2, 0.0]),
                    block([0.08, 0.4, 0.4], [-0.32, 0.4, 0.0]),
                    block([0.4, 0.3, 0.06], [0.0, 0.3, 0.34]),
                    block([0.4, 0.3, 0.06], [0.0, 0.3, -0.34]),
                ],
                ObjectPose::new(1.6, 3.3, 0.0),
            ),
            movable(
                "stool-0",
                MovableCategory::PierStool,
                "stool_example",
                vec![Part::Cylinder { radius: 0.2, half_height: 0.225, offset: [0.0, 0.225, 0.0], yaw: 0.0 }],
                ObjectPose::new(3.2, 0.8, 0.0),
            ),
        ],
        agent: AgentStart { x: 2.25, z: 0.87, heading: Heading::new(0).expect("valid heading") },
        horizon: 200,
        expert_trajectory: Vec::new(),
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    use Action::*;
    let mut scene = target_scene();
    let compiled = std::sync::Arc::new(CompiledScene::for_backward_construction(scene.clone(), Rules::default())?);
    let mut episode = Episode::new(compiled, EpisodeConfig::default())?;
    // Swing the stool aside, then drive to the armchair and pull it back from its place.
    let script = [
        Fetch,
        TurnLeft,
        Release,
        TurnRight,
        TurnRight,
        TurnRight,
        TurnRight,
        TurnRight,
        TurnRight,
        TurnRight,
        MoveForward,
        MoveForward,
        MoveForward,
        TurnLeft,
        TurnLeft,
        MoveForward,
        MoveForward,
        MoveForward,
        Fetch,
        MoveBackward,
        MoveBackward,
        MoveBackward,
        MoveBackward,
        Release,
    ];
    for (i, &action) in script.iter().enumerate() {
        let outcome = episode.step(action)?;
        if !outcome.accepted {
            return Err(format!(
                "step {i} ({}) was not accepted: {outcome:?}\nagent {:?}",
                action.name(),
                episode.agent_pose()
            )
            .into());
        }
    }
    for (i, object) in scene.movable_objects.iter_mut().enumerate() {
        object.pose = episode.object_poses()[i];
    }
    let agent = episode.agent_pose();
    scene.agent = AgentStart { x: agent.position.x, z: agent.position.z, heading: agent.heading };
    scene.expert_trajectory = reverse_trajectory(&script);
    // The shipped scene must validate and its expert must succeed.
    let compiled = CompiledScene::shared(scene.clone())?;
    let mut replay = Episode::new(compiled, EpisodeConfig::default())?;
    for &action in &scene.expert_trajectory {
        replay.step(action)?;
    }
    if !replay.metrics().success {
        return Err(format!("the expert does not succeed: {:?}", replay.metrics()).into());
    }
    println!("{}", scene.to_json_pretty());
    Ok(())
}
