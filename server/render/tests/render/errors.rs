//! Errors are values: bad requests never panic.

use esrp_render::{CHUNK_VIEWS, Camera, RenderError, Renderer, RendererConfig, ViewRequest};

use crate::common::{bedroom, ego_at, pose, renderer, start};

#[test]
fn bad_requests_are_errors() {
    let scene = bedroom();
    let handle = renderer().upload_scene(&scene).unwrap();
    let (camera, now) = start(&scene);
    let ok = ViewRequest::new(&handle, Camera::Ego(camera), &now);

    let too_few = [pose(1.0, 1.0, 0.0)];
    let err = renderer().render_one(&ViewRequest { object_poses: &too_few, ..ok }).unwrap_err();
    assert!(matches!(err, RenderError::InvalidPoses { view: 0, .. }), "{err}");

    let mut nan = now.clone();
    nan[0].x = f64::NAN;
    let err = renderer().render_one(&ViewRequest { object_poses: &nan, ..ok }).unwrap_err();
    assert!(matches!(err, RenderError::InvalidPoses { .. }), "{err}");

    let mut bad_camera = ego_at(1.0, 1.0, 0);
    bad_camera.horizontal_fov = 0.0;
    let err = renderer().render_one(&ViewRequest { camera: Camera::Ego(bad_camera), ..ok }).unwrap_err();
    assert!(matches!(err, RenderError::InvalidPoses { .. }), "{err}");

    for resolution in [0, renderer().max_resolution() + 1] {
        let err = renderer().render_one(&ok.with_resolution(resolution)).unwrap_err();
        assert!(matches!(err, RenderError::InvalidResolution { .. }), "{err}");
    }

    // No batch is too large: more views or pixels than one submission holds are drawn in
    // chunks (`batch.rs` checks their pixels).
    let many = vec![ok; CHUNK_VIEWS + 1];
    assert_eq!(renderer().render_batch(&many).unwrap().len(), CHUNK_VIEWS + 1);
    let huge = vec![ok.with_resolution(renderer().max_resolution()); 2];
    assert_eq!(renderer().render_batch(&huge).unwrap().len(), 2);

    assert!(renderer().render_batch(&[]).unwrap().is_empty());
    // The renderer still works after all that.
    assert!(renderer().render_one(&ok).is_ok());
}

#[test]
fn scenes_of_another_renderer_are_rejected() {
    let other = Renderer::new(RendererConfig::default()).unwrap();
    let scene = bedroom();
    let foreign = other.upload_scene(&scene).unwrap();
    let (camera, now) = start(&scene);
    let err = renderer().render_one(&ViewRequest::new(&foreign, Camera::Ego(camera), &now)).unwrap_err();
    assert!(matches!(err, RenderError::ForeignScene { view: 0 }), "{err}");
}

#[test]
fn no_adapter_error_says_how_to_fix_it() {
    let message = RenderError::NoAdapter { tried: "vulkan, gl".into() }.to_string();
    assert!(message.contains("mesa-vulkan-drivers"), "{message}");
}
