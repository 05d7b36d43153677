//! Golden images: renders of fixed scenes compared with PNGs in `tests/goldens/`.
//!
//! Regenerate after an intended change with `ESRP_UPDATE_GOLDENS=1 cargo test -p esrp-render`,
//! then look at the new PNGs before committing them.
//!
//! Tolerance: a pixel differs when any channel differs by more than 2 (rounding of a driver's
//! colour conversion); at most 0.25 % of the pixels (41 of 128×128) may differ (edge pixels
//! whose coverage a rasteriser decides differently). An object that moves by a pixel, changes
//! colour or disappears changes far more pixels than that.

use std::path::PathBuf;

use esrp_render::{Camera, ViewRequest, decode_png_rgb, encode_png_rgb};

use crate::common::{bedroom, renderer, showcase, start, targets};

const CHANNEL_TOLERANCE: u8 = 2;
const MAX_DIFFERING_FRACTION: f64 = 0.0025;

fn golden_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/goldens").join(format!("{name}.png"))
}

/// Compares `rgb` with the golden `name`, or rewrites the golden when `ESRP_UPDATE_GOLDENS=1`.
fn check_golden(name: &str, rgb: &[u8], resolution: u32) {
    let path = golden_path(name);
    if std::env::var("ESRP_UPDATE_GOLDENS").is_ok_and(|v| v == "1") {
        std::fs::write(&path, encode_png_rgb(rgb, resolution, resolution).unwrap()).unwrap();
        eprintln!("updated {}", path.display());
        return;
    }
    let data = std::fs::read(&path).unwrap_or_else(|e| {
        panic!(
            "golden {} is missing ({e}); create it with ESRP_UPDATE_GOLDENS=1 cargo test -p esrp-render",
            path.display()
        )
    });
    let (golden, w, h) = decode_png_rgb(&data).unwrap();
    assert_eq!((w, h), (resolution, resolution), "golden {name} has another size");
    let differing = golden
        .chunks_exact(3)
        .zip(rgb.chunks_exact(3))
        .filter(|(a, b)| a.iter().zip(b.iter()).any(|(x, y)| x.abs_diff(*y) > CHANNEL_TOLERANCE))
        .count();
    let allowed = (MAX_DIFFERING_FRACTION * f64::from(resolution * resolution)).floor() as usize;
    if differing > allowed {
        let actual = std::env::temp_dir().join(format!("esrp-render-{name}-actual.png"));
        let _ = std::fs::write(&actual, encode_png_rgb(rgb, resolution, resolution).unwrap());
        panic!(
            "{name}: {differing} pixels differ from the golden (at most {allowed} may); the render is at {}. \
             If the change is intended, run ESRP_UPDATE_GOLDENS=1 cargo test -p esrp-render",
            actual.display()
        );
    }
}

#[test]
fn bedroom_ego_goal_and_current_match_goldens() {
    let scene = bedroom();
    let handle = renderer().upload_scene(&scene).unwrap();
    let (camera, current) = start(&scene);
    let goal = targets(&scene);
    let out = renderer()
        .render_batch(&[
            ViewRequest::new(&handle, Camera::Ego(camera), &current),
            ViewRequest::new(&handle, Camera::TopDown, &goal),
            ViewRequest::new(&handle, Camera::TopDown, &current),
        ])
        .unwrap();
    check_golden("bedroom_ego", &out[0].rgb, 128);
    check_golden("bedroom_goal", &out[1].rgb, 128);
    check_golden("bedroom_current", &out[2].rgb, 128);
}

#[test]
fn showcase_ego_and_goal_match_goldens() {
    let scene = showcase();
    let handle = renderer().upload_scene(&scene).unwrap();
    let (camera, current) = start(&scene);
    let goal = targets(&scene);
    let out = renderer()
        .render_batch(&[
            ViewRequest::new(&handle, Camera::Ego(camera), &current),
            ViewRequest::new(&handle, Camera::TopDown, &goal),
        ])
        .unwrap();
    check_golden("showcase_ego", &out[0].rgb, 128);
    check_golden("showcase_goal", &out[1].rgb, 128);
}
