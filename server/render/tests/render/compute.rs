//! The compute rasteriser against the graphics pipeline: the same views, the same images up to
//! the rounding of edges (a pixel centre on or next to a triangle's edge may fall either side)
//! and of depth; the same batch twice, the same bytes.

use esrp_core::{EgoCamera, ObjectPose};
use esrp_render::{Camera, Outputs, Rasterizer, Renderer, RendererConfig, Timestamps, ViewOutput, ViewRequest};

use crate::common::{backend, bedroom, ego_at, renderer, scattered_cameras, showcase, start, targets};

/// The compute rasteriser, timing its device (as on a GPU; the tests' adapters have timestamp
/// queries).
fn compute_renderer() -> Renderer {
    Renderer::new(RendererConfig {
        backends: backend(),
        rasterizer: Rasterizer::Compute,
        timestamps: Timestamps::On,
        ..RendererConfig::default()
    })
    .unwrap_or_else(|e| panic!("the compute rasteriser needs an adapter with compute shaders: {e}"))
}

/// How two renderings of one view differ: the share of pixels whose RGB differ, and the share
/// that differ by more than one step in some channel.
fn differing(a: &ViewOutput, b: &ViewOutput) -> (f64, f64) {
    let pixels = a.rgb.len() / 3;
    let (mut any, mut more) = (0usize, 0usize);
    for (p, q) in a.rgb.chunks_exact(3).zip(b.rgb.chunks_exact(3)) {
        let step = p.iter().zip(q).map(|(x, y)| x.abs_diff(*y)).max().unwrap_or(0);
        any += usize::from(step > 0);
        more += usize::from(step > 1);
    }
    (any as f64 / pixels as f64, more as f64 / pixels as f64)
}

/// Ego views from all over two rooms (near walls and furniture: triangles crossing the camera's
/// plane), goal top-down views, several resolutions, with depth and segmentation.
#[test]
fn compute_views_match_the_pipeline_s() {
    let pipeline = renderer();
    let compute = compute_renderer();
    assert_eq!(compute.rasterizer(), Rasterizer::Compute);
    for scene in [bedroom(), showcase()] {
        let on_pipeline = pipeline.upload_scene(&scene).unwrap();
        let on_compute = compute.upload_scene(&scene).unwrap();
        let (start_camera, poses) = start(&scene);
        let goal = targets(&scene);
        let mut cameras: Vec<EgoCamera> = scattered_cameras(7, 40);
        cameras.push(start_camera);
        // Right against the walls, looking at them and along them.
        cameras.extend((0..16).map(|k| ego_at(0.12, 0.12, k)));
        let views = |handle| {
            let mut views: Vec<ViewRequest<'_>> = cameras
                .iter()
                .enumerate()
                .map(|(i, camera)| {
                    let request = ViewRequest::new(handle, Camera::Ego(*camera), &poses);
                    match i % 4 {
                        0 => request.with_outputs(Outputs::ALL),
                        1 => request.with_resolution(64),
                        2 => request.with_resolution(100),
                        _ => request,
                    }
                })
                .collect();
            views.push(ViewRequest::new(handle, Camera::TopDown, &goal));
            views.push(ViewRequest::new(handle, Camera::TopDown, &poses).with_outputs(Outputs::ALL));
            views
        };
        let expected = pipeline.render_batch(&views(&on_pipeline)).unwrap();
        let got = compute.render_batch(&views(&on_compute)).unwrap();
        let (again, timings) = compute.render_batch_timed(&views(&on_compute)).unwrap();
        // The compute pass is timed as the render passes are.
        assert!(timings.gpu.is_some_and(|d| d > std::time::Duration::ZERO), "{timings:?}");
        let (mut worst_any, mut worst_more) = (0.0f64, 0.0f64);
        for (i, (e, g)) in expected.iter().zip(&got).enumerate() {
            assert_eq!((e.resolution, e.rgb.len()), (g.resolution, g.rgb.len()), "view {i}");
            let (any, more) = differing(e, g);
            worst_any = worst_any.max(any);
            worst_more = worst_more.max(more);
            assert!(
                any < 0.005 && more < 0.005,
                "{}: view {i}: {any:.4} of pixels differ, {more:.4} by more than a step",
                scene.scene().id
            );
            assert_eq!(g, &again[i], "view {i}: the same batch twice");
            if let (Some(ed), Some(gd)) = (&e.depth, &g.depth) {
                let (es, gs) = (e.segmentation.as_ref().unwrap(), g.segmentation.as_ref().unwrap());
                let same = es.iter().zip(gs).filter(|(a, b)| a == b).count();
                assert!(same as f64 > 0.97 * es.len() as f64, "view {i}: segmentation {same} of {}", es.len());
                for ((a, b), (sa, sb)) in ed.iter().zip(gd).zip(es.iter().zip(gs)) {
                    if sa == sb && a.is_finite() {
                        assert!((a - b).abs() <= 1e-3 * a.abs().max(1.0), "view {i}: depth {a} against {b}");
                    }
                }
            }
        }
        eprintln!(
            "{}: at most {worst_any:.4} of a view's pixels differ, {worst_more:.4} by more than a step",
            scene.scene().id
        );
    }
}

/// A view alone and the same view among others: the same bytes (each view its own dispatch,
/// every pixel written).
#[test]
fn a_compute_view_is_the_same_alone_and_in_a_batch() {
    let compute = compute_renderer();
    let scene = bedroom();
    let handle = compute.upload_scene(&scene).unwrap();
    let (camera, poses) = start(&scene);
    let cameras = scattered_cameras(11, 12);
    let mut batch: Vec<ViewRequest<'_>> =
        cameras.iter().map(|c| ViewRequest::new(&handle, Camera::Ego(*c), &poses)).collect();
    batch.insert(5, ViewRequest::new(&handle, Camera::Ego(camera), &poses));
    let alone = compute.render_one(&ViewRequest::new(&handle, Camera::Ego(camera), &poses)).unwrap();
    assert_eq!(compute.render_batch(&batch).unwrap()[5], alone);
    let moved: Vec<ObjectPose> = poses.iter().map(|p| ObjectPose::new(p.x + 0.3, p.z, p.yaw)).collect();
    let other = compute.render_one(&ViewRequest::new(&handle, Camera::Ego(camera), &moved)).unwrap();
    assert_ne!(other, alone, "the objects' poses reach the compute rasteriser");
}
