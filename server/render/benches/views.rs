//! Throughput of the renderer alone (no server): views per second for one view per submit and
//! for batches of 16 to 256 egocentric views of furnished rooms at 128×128, the same 256 views at
//! 64×64 and 256×256, a top-down batch and a batch with depth and segmentation, each with frustum
//! culling on and off. `cargo bench -p esrp-render --bench views`; `ESRP_BENCH_SECONDS` sets the
//! time per case (default 3), `ESRP_BENCH_CASES` picks cases by name (comma-separated; see
//! `CASES`), `ESRP_BENCH_CULL` one column (`on` or `off`), `ESRP_BENCH_JSON` a file to write
//! the figures to as well, `ESRP_BENCH_START_AT` (Unix time, seconds) when to start measuring
//! (several processes measuring together), `ESRP_RENDER_BACKEND=gl` measures OpenGL and
//! `ESRP_RENDER_RASTERIZER=compute` the compute rasteriser (culling does not apply to it).
//! `scripts/gpu-bench.sh` runs it on a lent GPU machine, alone and as several processes at once
//! (whether one device, not the server, is what caps). Where the adapter has timestamp queries,
//! each cell also says how many microseconds a view took the device to draw, by its own clock
//! (in brackets; `gpu_us_per_view` in the JSON): the rest of a view's time is the submission,
//! the wait and the readback (the timestamps are a GPU's by default; `ESRP_RENDER_TIMESTAMPS=on`
//! or `off` asks for them or not, on any adapter). `ESRP_RENDER_DEPTH_BUFFERS=per-page` gives each
//! view's pass a depth buffer of its own (default `shared`).

use std::sync::Arc;
use std::time::{Duration, Instant};

use esrp_core::{CompiledScene, EgoCamera, FixedObject, Heading, ObjectPose, Part, Scene, Shape};
use esrp_render::{
    Camera, DepthBuffers, Outputs, Rasterizer, Renderer, RendererConfig, SceneHandle, Timestamps, ViewRequest,
};

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

/// Renders `requests` over and over for `seconds`; returns the views per second, and the
/// device's drawing per view in microseconds where the renderer times it.
fn run(renderer: &Renderer, requests: &[ViewRequest<'_>], seconds: f64) -> (f64, Option<f64>) {
    for _ in 0..3 {
        renderer.render_batch(requests).unwrap();
    }
    let start = Instant::now();
    let (mut views, mut drawing) = (0usize, Some(Duration::ZERO));
    while start.elapsed() < Duration::from_secs_f64(seconds) {
        let (outputs, timings) = renderer.render_batch_timed(requests).unwrap();
        views += outputs.len();
        drawing = drawing.zip(timings.gpu).map(|(sum, batch)| sum + batch);
    }
    let per_view = drawing.map(|d| d.as_secs_f64() * 1e6 / views.max(1) as f64);
    (views as f64 / start.elapsed().as_secs_f64(), per_view)
}

/// The cases, by the name `ESRP_BENCH_CASES` selects them with: egocentric batches of 1 to 256
/// views at 128×128, the same 256 at 64×64 and 256×256 (whether the device's time follows the
/// pixels or the triangles), 256 top-down views, and 256 with depth and segmentation.
const CASES: [&str; 9] =
    ["ego-1", "ego-16", "ego-64", "ego-256", "ego-256-64px", "ego-256-256px", "top-256", "full-256", "ego-1024"];

/// The cases to run: `ESRP_BENCH_CASES` (comma-separated names of [`CASES`]), else all but
/// `ego-1024`. An unknown name is an error that lists the known ones.
fn selected_cases() -> Vec<&'static str> {
    let Ok(list) = std::env::var("ESRP_BENCH_CASES") else {
        return CASES.iter().copied().filter(|c| *c != "ego-1024").collect();
    };
    list.split(',')
        .map(str::trim)
        .filter(|name| !name.is_empty())
        .map(|name| {
            CASES.iter().copied().find(|c| *c == name).unwrap_or_else(|| {
                eprintln!("views: unknown case {name:?} in ESRP_BENCH_CASES (known: {})", CASES.join(", "));
                std::process::exit(2)
            })
        })
        .collect()
}

/// Which of the two renderers to measure: `ESRP_BENCH_CULL` = `on`, `off` or `both` (default).
fn selected_culling() -> Vec<bool> {
    match std::env::var("ESRP_BENCH_CULL").as_deref() {
        Err(_) | Ok("both") => vec![true, false],
        Ok("on") => vec![true],
        Ok("off") => vec![false],
        Ok(other) => {
            eprintln!("views: ESRP_BENCH_CULL is on, off or both, not {other:?}");
            std::process::exit(2)
        }
    }
}

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --benches` passes nothing: run briefly then.
    let benching = std::env::args().any(|a| a == "--bench");
    let seconds: f64 = std::env::var("ESRP_BENCH_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(if benching {
        3.0
    } else {
        0.05
    });
    let cases = selected_cases();
    let culling = selected_culling();
    let backends = esrp_render::BackendPreference::from_env().unwrap_or_default();
    let rasterizer: Rasterizer = match std::env::var("ESRP_RENDER_RASTERIZER") {
        Ok(name) => name.parse().unwrap_or_else(|e| {
            eprintln!("views: ESRP_RENDER_RASTERIZER: {e}");
            std::process::exit(2)
        }),
        Err(_) => Rasterizer::default(),
    };
    let timestamps: Timestamps = match std::env::var("ESRP_RENDER_TIMESTAMPS") {
        Ok(name) => name.parse().unwrap_or_else(|e| {
            eprintln!("views: ESRP_RENDER_TIMESTAMPS: {e}");
            std::process::exit(2)
        }),
        Err(_) => Timestamps::default(),
    };
    let depth_buffers: DepthBuffers = match std::env::var("ESRP_RENDER_DEPTH_BUFFERS") {
        Ok(name) => name.parse().unwrap_or_else(|e| {
            eprintln!("views: ESRP_RENDER_DEPTH_BUFFERS: {e}");
            std::process::exit(2)
        }),
        Err(_) => DepthBuffers::default(),
    };
    let renderers: Vec<Renderer> = culling
        .iter()
        .map(|&cull| {
            let config = RendererConfig { backends, cull, rasterizer, timestamps, depth_buffers, ..Default::default() };
            Renderer::new(config).unwrap_or_else(|e| panic!("{e}"))
        })
        .collect();
    let info = renderers[0].adapter_info();
    println!("adapter: {} ({:?}, {}), rasterizer {rasterizer}", info.name, info.backend, info.driver_info);
    let scenes = scenes();
    let handles: Vec<Vec<Arc<SceneHandle>>> =
        renderers.iter().map(|r| scenes.iter().map(|s| r.upload_scene(s).unwrap()).collect()).collect();
    for h in &handles[0] {
        println!("scene {}: {} triangles", h.scene_id(), h.triangle_count());
    }
    let poses: Vec<Vec<ObjectPose>> =
        scenes.iter().map(|s| s.scene().movable_objects.iter().map(|o| o.pose).collect()).collect();
    let cameras: Vec<EgoCamera> = (0..1024).map(camera).collect();
    // The requests of case `name` on renderer `r`.
    let requests = |r: usize, name: &str| -> Vec<ViewRequest<'_>> {
        let handles = &handles[r];
        let view = |i: usize, camera| ViewRequest::new(&handles[i % handles.len()], camera, &poses[i % handles.len()]);
        let ego = |n: usize| (0..n).map(|i| view(i, Camera::Ego(cameras[i]))).collect::<Vec<_>>();
        match name {
            "ego-1" => ego(1),
            "ego-16" => ego(16),
            "ego-64" => ego(64),
            "ego-256" => ego(256),
            "ego-1024" => ego(1024),
            "ego-256-64px" => ego(256).into_iter().map(|q| q.with_resolution(64)).collect(),
            "ego-256-256px" => ego(256).into_iter().map(|q| q.with_resolution(256)).collect(),
            "top-256" => (0..256).map(|i| view(i, Camera::TopDown)).collect(),
            "full-256" => ego(256).into_iter().map(|q| q.with_outputs(Outputs::ALL)).collect(),
            _ => unreachable!("cases are checked by selected_cases"),
        }
    };
    let columns: Vec<&str> = culling.iter().map(|&on| if on { "culling on" } else { "culling off" }).collect();
    wait_for_start();
    let timed = renderers.iter().all(Renderer::times_device);
    print!("{:<34}", if timed { "case, views/s (device µs/view)" } else { "case, views/s" });
    for column in &columns {
        print!(" {column:>20}");
    }
    println!();
    let mut figures = Vec::new();
    for name in cases {
        print!("{name:<34}");
        let mut row = Vec::new();
        for (r, renderer) in renderers.iter().enumerate() {
            let (views, drawing) = run(renderer, &requests(r, name), seconds);
            match drawing {
                Some(us) => print!(" {:>20}", format!("{views:.0} ({us:.1})")),
                None => print!(" {views:>20.0}"),
            }
            row.push((views, drawing));
        }
        println!();
        figures.push((name, row));
    }
    if let Ok(path) = std::env::var("ESRP_BENCH_JSON") {
        // One table of the cases' cells, by `pick`ing a figure of each.
        let table = |pick: fn(&(f64, Option<f64>)) -> serde_json::Value| -> serde_json::Map<String, serde_json::Value> {
            figures
                .iter()
                .map(|(name, row)| {
                    let cells = columns.iter().zip(row).map(|(column, cell)| ((*column).to_owned(), pick(cell)));
                    ((*name).to_owned(), serde_json::Value::Object(cells.collect()))
                })
                .collect()
        };
        let json = serde_json::json!({
            "adapter": format!("{} ({:?}, {})", info.name, info.backend, info.driver_info),
            "rasterizer": rasterizer.name(),
            "depth_buffers": depth_buffers.name(),
            "seconds": seconds,
            "cases": table(|(views, _)| (*views).into()),
            "gpu_us_per_view": timed.then(|| table(|(_, drawing)| (*drawing).into())),
        });
        std::fs::write(&path, format!("{json}\n")).unwrap_or_else(|e| panic!("cannot write {path}: {e}"));
    }
}

/// Sleeps until `ESRP_BENCH_START_AT` (Unix time in seconds), if it is set and still ahead.
fn wait_for_start() {
    let Some(start) = std::env::var("ESRP_BENCH_START_AT").ok().and_then(|s| s.parse::<f64>().ok()) else { return };
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64());
    if start > now {
        std::thread::sleep(Duration::from_secs_f64(start - now));
    }
}
