//! Renders a scene file's start egocentric view, goal image and current top-down view.
//!
//! `cargo run -p esrp-render --example render_scene -- SCENE.json OUT_DIR [RESOLUTION]` writes
//! `OUT_DIR/ego.png`, `OUT_DIR/goal.png` and `OUT_DIR/current.png`. `ESRP_RENDER_BACKEND=gl`
//! forces the OpenGL backend.

use std::path::PathBuf;

use esrp_core::{CompiledScene, Scene};
use esrp_render::{BackendPreference, Renderer, RendererConfig, render_scene_pngs};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let usage = "usage: render_scene SCENE.json OUT_DIR [RESOLUTION]";
    let scene_path = PathBuf::from(args.next().ok_or(usage)?);
    let out_dir = PathBuf::from(args.next().ok_or(usage)?);
    let resolution: u32 = args.next().map(|r| r.parse()).transpose()?.unwrap_or(esrp_render::DEFAULT_RESOLUTION);

    let scene = CompiledScene::shared(Scene::from_json(&std::fs::read_to_string(&scene_path)?)?)?;
    let backends = BackendPreference::from_env().unwrap_or_default();
    let renderer = Renderer::new(RendererConfig { backends, ..RendererConfig::default() })?;
    let info = renderer.adapter_info();
    eprintln!("adapter: {} ({:?}, {})", info.name, info.backend, info.driver_info);

    let pngs = render_scene_pngs(&renderer, &scene, resolution)?;
    std::fs::create_dir_all(&out_dir)?;
    for (name, png) in [("ego.png", pngs.ego), ("goal.png", pngs.goal), ("current.png", pngs.current)] {
        std::fs::write(out_dir.join(name), png)?;
    }
    eprintln!("wrote ego.png, goal.png, current.png to {}", out_dir.display());
    Ok(())
}
