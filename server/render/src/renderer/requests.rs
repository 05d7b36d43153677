//! What the renderer is asked and answers: uploaded scenes ([`SceneHandle`]), views
//! ([`ViewRequest`] with its [`Outputs`]) and their images ([`ViewOutput`]), and the check of a
//! batch of requests ([`validate`]).

use bytes::Bytes;
use esrp_core::ObjectPose;

use crate::camera::{Camera, TopDownFrame};
use crate::error::RenderError;
use crate::mesh::MeshPart;

use super::limits::DEFAULT_RESOLUTION;

/// A scene's geometry on the device, uploaded once by [`Renderer::upload_scene`](crate::Renderer::upload_scene) and shared by
/// every view of every episode of that scene (wrap it in an `Arc`; caching by scene id is the
/// caller's job).
#[derive(Debug)]
pub struct SceneHandle {
    pub(super) renderer_id: u64,
    pub(super) scene_id: String,
    pub(super) vertex_buffer: wgpu::Buffer,
    pub(super) index_buffer: wgpu::Buffer,
    /// The vertex and index buffers bound for the compute rasteriser, when the renderer uses it.
    pub(super) raster_bind_group: Option<wgpu::BindGroup>,
    pub(super) index_count: u32,
    pub(super) parts: Vec<MeshPart>,
    pub(super) vertex_count: usize,
    pub(super) movable_count: usize,
    pub(super) frame: TopDownFrame,
    pub(super) max_height: f64,
}

impl SceneHandle {
    /// The scene's id.
    pub fn scene_id(&self) -> &str {
        &self.scene_id
    }

    /// Number of movable objects: the length every view's `object_poses` must have.
    pub fn movable_count(&self) -> usize {
        self.movable_count
    }

    /// Number of triangles drawn per view.
    pub fn triangle_count(&self) -> usize {
        self.index_count as usize / 3
    }

    /// Number of vertices on the device.
    pub fn vertex_count(&self) -> usize {
        self.vertex_count
    }

    /// The top-down view's frame at `resolution` (same as [`TopDownFrame::for_scene`]).
    pub fn top_down_frame(&self, resolution: u32) -> TopDownFrame {
        self.frame.with_resolution(resolution)
    }
}

/// Which images a view produces besides RGB.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Outputs {
    /// View depth in metres (`f32`), [`f32::INFINITY`] where nothing is drawn.
    pub depth: bool,
    /// Instance segmentation ([`crate::SegmentLabel`] ids).
    pub segmentation: bool,
}

impl Outputs {
    /// RGB only.
    pub const RGB: Outputs = Outputs { depth: false, segmentation: false };
    /// RGB, depth and segmentation.
    pub const ALL: Outputs = Outputs { depth: true, segmentation: true };

    pub(super) fn any_extra(self) -> bool {
        self.depth || self.segmentation
    }
}

/// One view to render.
#[derive(Clone, Copy, Debug)]
pub struct ViewRequest<'a> {
    /// The scene, uploaded by the same renderer.
    pub scene: &'a SceneHandle,
    /// The camera.
    pub camera: Camera,
    /// One pose per movable object, in scene order: current poses for the egocentric and
    /// current top-down views, target poses for the goal image.
    pub object_poses: &'a [ObjectPose],
    /// Extra images wanted.
    pub outputs: Outputs,
    /// Width and height, pixels.
    pub resolution: u32,
}

impl<'a> ViewRequest<'a> {
    /// An RGB view at [`DEFAULT_RESOLUTION`].
    pub fn new(scene: &'a SceneHandle, camera: Camera, object_poses: &'a [ObjectPose]) -> Self {
        Self { scene, camera, object_poses, outputs: Outputs::RGB, resolution: DEFAULT_RESOLUTION }
    }

    /// The same view with other outputs.
    pub fn with_outputs(self, outputs: Outputs) -> Self {
        Self { outputs, ..self }
    }

    /// The same view at another resolution.
    pub fn with_resolution(self, resolution: u32) -> Self {
        Self { resolution, ..self }
    }
}

/// The images of one view. All are row-major, top row first, `resolution × resolution`.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewOutput {
    /// Width and height, pixels.
    pub resolution: u32,
    /// Tightly packed RGB, 3 bytes per pixel.
    pub rgb: Bytes,
    /// View depth in metres along the camera's axis, if asked for; [`f32::INFINITY`] where
    /// nothing is drawn.
    pub depth: Option<Vec<f32>>,
    /// Segmentation ids ([`crate::SegmentLabel::id`]), if asked for.
    pub segmentation: Option<Vec<u32>>,
}

/// Checks a batch before anything is drawn: every view's scene was uploaded by the renderer
/// `renderer_id`, its resolution is in `1..=max_resolution`, it has one finite pose per movable
/// object and an egocentric camera is finite with a field of view in (0, π).
pub(super) fn validate(requests: &[ViewRequest<'_>], renderer_id: u64, max_resolution: u32) -> Result<(), RenderError> {
    for (view, request) in requests.iter().enumerate() {
        if request.scene.renderer_id != renderer_id {
            return Err(RenderError::ForeignScene { view });
        }
        if request.resolution == 0 || request.resolution > max_resolution {
            return Err(RenderError::InvalidResolution { resolution: request.resolution, max: max_resolution });
        }
        if request.object_poses.len() != request.scene.movable_count {
            return Err(RenderError::InvalidPoses {
                view,
                reason: format!(
                    "{} poses given for a scene with {} movable objects",
                    request.object_poses.len(),
                    request.scene.movable_count
                ),
            });
        }
        if request.object_poses.iter().any(|p| !(p.x.is_finite() && p.z.is_finite() && p.yaw.is_finite())) {
            return Err(RenderError::InvalidPoses { view, reason: "a pose is not finite".into() });
        }
        if let Camera::Ego(camera) = request.camera {
            let finite = camera.eye.iter().all(|c| c.is_finite())
                && camera.yaw.is_finite()
                && camera.pitch.is_finite()
                && camera.horizontal_fov > 0.0
                && camera.horizontal_fov < std::f64::consts::PI;
            if !finite {
                return Err(RenderError::InvalidPoses {
                    view,
                    reason: "the egocentric camera is not finite or its field of view is not in (0, π)".into(),
                });
            }
        }
    }
    Ok(())
}
