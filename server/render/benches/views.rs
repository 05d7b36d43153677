//! Throughput of the renderer: views per second for one view per submit and for batches of
//! 16, 64 and 256 egocentric views of furnished rooms at 128×128 (plus a top-down batch and a
//! batch with depth and segmentation). `cargo bench -p esrp-render`; set `ESRP_BENCH_SECONDS`
//! to change the time per case (default 3) and `ESRP_RENDER_BACKEND=gl` to measure OpenGL.

use std::sync::Arc;
use std::time::{Duration, Instant};

use esrp_core::{CompiledScene, EgoCamera, FixedObject, Heading, ObjectPose, Part, Scene, Shape};
use esrp_render::{Camera, Outputs, Renderer, RendererConfig, SceneHandle, ViewRequest};

/// The example bedroom, and a copy with more furniture along the walls (a fuller room).
fn scenes() -> Vec<Arc<CompiledScene>> {
    let text = include_str!("../../core/examples/scenes/bedroom.json");
    let bedroom = Scene::from_json(text).unwrap();
    let mut furnished = bedroom.clone();
    furnished.id = "bench/furnished".into();
    let shelf = |x: f64, z: f64| FixedObject {
        id: format!("shelf-{x}-{z}"),
        category: "shelf".into(),
        model: String::new(),
        shape: Shape::Parts(vec![
            Part::Box { half_extents: [0.3, 0.9, 0.15], offset: [0.0, 0.9, 0.0], yaw: 0.0 },
            Part::Cylinder { radius: 0.1, half_height: 0.15, offset: [0.0, 1.95, 0.0], yaw: 0.0 },
        ]),
        pose: ObjectPose::new(x, z, 0.0),
    };
    furnished.fixed_objects.extend([shelf(3.6, 0.2), shelf(4.3, 0.2)]);
    let furnished = CompiledScene::shared(furnished).unwrap_or_else(|e| panic!("bench scene: {e}"));
    vec![CompiledScene::shared(bedroom).unwrap(), furnished]
}

fn camera(i: usize) -> EgoCamera {
    let k = (i % 16) as u8;
    EgoCamera {
        eye: [1.2 + 0.01 * (i % 100) as f64, 1.25, 1.2 + 0.005 * (i % 200) as f64],
        yaw: Heading::new(k).unwrap().yaw(),
        pitch: 20f64.to_radians(),
        horizontal_fov: 90f64.to_radians(),
    }
}

fn run(renderer: &Renderer, requests: &[ViewRequest<'_>], seconds: f64) -> f64 {
    for _ in 0..3 {
        renderer.render_batch(requests).unwrap();
    }
    let start = Instant::now();
    let mut views = 0usize;
    while start.elapsed() < Duration::from_secs_f64(seconds) {
        views += renderer.render_batch(requests).unwrap().len();
    }
    views as f64 / start.elapsed().as_secs_f64()
}

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --benches` passes nothing: run briefly then.
    let benching = std::env::args().any(|a| a == "--bench");
    let seconds: f64 = std::env::var("ESRP_BENCH_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(if benching {
        3.0
    } else {
        0.05
    });
    let backends = esrp_render::BackendPreference::from_env().unwrap_or_default();
    // The same cases with culling on (the default) and off.
    let renderers: Vec<Renderer> = [true, false]
        .into_iter()
        .map(|cull| {
            Renderer::new(RendererConfig { backends, cull, ..RendererConfig::default() })
                .unwrap_or_else(|e| panic!("{e}"))
        })
        .collect();
    let info = renderers[0].adapter_info();
    println!("adapter: {} ({:?}, {})", info.name, info.backend, info.driver_info);
    let scenes = scenes();
    let handles: Vec<Vec<Arc<SceneHandle>>> =
        renderers.iter().map(|r| scenes.iter().map(|s| r.upload_scene(s).unwrap()).collect()).collect();
    for h in &handles[0] {
        println!("scene {}: {} triangles", h.scene_id(), h.triangle_count());
    }
    let poses: Vec<Vec<ObjectPose>> =
        scenes.iter().map(|s| s.scene().movable_objects.iter().map(|o| o.pose).collect()).collect();
    let cameras: Vec<EgoCamera> = (0..256).map(camera).collect();
    let ego = |r: usize, n: usize| -> Vec<ViewRequest<'_>> {
        let handles = &handles[r];
        (0..n)
            .map(|i| ViewRequest::new(&handles[i % handles.len()], Camera::Ego(cameras[i]), &poses[i % handles.len()]))
            .collect()
    };
    fn both<'a>(renderers: &[Renderer], seconds: f64, case: impl Fn(usize) -> Vec<ViewRequest<'a>>) -> [f64; 2] {
        [0, 1].map(|r| run(&renderers[r], &case(r), seconds))
    }
    println!("{:<34} {:>12} {:>12}", "case (128x128), views/s", "culling on", "culling off");
    for n in [1, 16, 64, 256] {
        let [on, off] = both(&renderers, seconds, |r| ego(r, n));
        println!("{:<34} {:>12.0} {:>12.0}", format!("ego, batch of {n}"), on, off);
    }
    let top = |r: usize| -> Vec<ViewRequest<'_>> {
        let handles = &handles[r];
        (0..256)
            .map(|i| ViewRequest::new(&handles[i % handles.len()], Camera::TopDown, &poses[i % handles.len()]))
            .collect()
    };
    let [on, off] = both(&renderers, seconds, top);
    println!("{:<34} {:>12.0} {:>12.0}", "top-down, batch of 256", on, off);
    let full =
        |r: usize| -> Vec<ViewRequest<'_>> { ego(r, 256).into_iter().map(|q| q.with_outputs(Outputs::ALL)).collect() };
    let [on, off] = both(&renderers, seconds, full);
    println!("{:<34} {:>12.0} {:>12.0}", "ego + depth + seg, batch of 256", on, off);
}
