//! Cameras: the egocentric perspective camera (SPEC §2) and the top-down orthographic frame
//! (SPEC §1, §4), with the exact pixel ↔ floor mapping of the top-down view.
//!
//! Pixel coordinates are continuous `(col, row)` with the origin at the top-left corner of the
//! image: pixel `(c, r)` covers `[c, c + 1) × [r, r + 1)` and its centre is `(c + 0.5, r + 0.5)`,
//! which is where the rasteriser samples it.

use esrp_core::{CompiledScene, EgoCamera};

use crate::gpu::{GpuView, MAX_POSE_SLOTS};

/// Near plane of the egocentric camera, metres.
pub const EGO_NEAR: f64 = 0.05;

/// Margin around the room (walls included) in the top-down view, metres.
pub const TOP_DOWN_MARGIN: f64 = 0.15;

/// Which camera a view uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Camera {
    /// The agent's egocentric perspective camera ([`Episode::ego_camera`](esrp_core::Episode::ego_camera)).
    Ego(EgoCamera),
    /// The top-down orthographic view of the whole room ([`TopDownFrame::for_scene`]).
    TopDown,
}

/// The square region of the floor that the top-down view shows, and its exact mapping to
/// pixels.
///
/// The view looks down −y; image right is +x and image up is −z (SPEC §1). It frames the
/// bounding box of the room's floor and walls plus [`TOP_DOWN_MARGIN`], centred, with square
/// pixels of `side / resolution` metres:
///
/// - `col = (x − min_x) / metres_per_pixel`, `row = (z − min_z) / metres_per_pixel`;
/// - `x = min_x + col · metres_per_pixel`, `z = min_z + row · metres_per_pixel`.
///
/// Pixel `(c, r)` is centred on `pixel_to_floor(c + 0.5, r + 0.5)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TopDownFrame {
    /// World x at the left edge of the image, metres.
    pub min_x: f64,
    /// World z at the top edge of the image, metres.
    pub min_z: f64,
    /// Side of the square region shown, metres.
    pub side: f64,
    /// Image width and height, pixels.
    pub resolution: u32,
}

impl TopDownFrame {
    /// The frame of a scene's top-down view at `resolution` × `resolution` pixels.
    pub fn for_scene(scene: &CompiledScene, resolution: u32) -> Self {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        let mut grow = |x: f64, z: f64| {
            lo = [lo[0].min(x), lo[1].min(z)];
            hi = [hi[0].max(x), hi[1].max(z)];
        };
        for p in scene.floor() {
            grow(p.x, p.z);
        }
        for piece in scene.wall_pieces() {
            for corner in piece.footprint().corners() {
                grow(corner.x, corner.z);
            }
        }
        if !(lo[0].is_finite() && lo[1].is_finite() && hi[0].is_finite() && hi[1].is_finite()) {
            lo = [-1.0, -1.0];
            hi = [1.0, 1.0];
        }
        let side = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(0.1) + 2.0 * TOP_DOWN_MARGIN;
        let centre = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
        Self { min_x: centre[0] - side / 2.0, min_z: centre[1] - side / 2.0, side, resolution: resolution.max(1) }
    }

    /// The same region at another resolution.
    pub fn with_resolution(self, resolution: u32) -> Self {
        Self { resolution: resolution.max(1), ..self }
    }

    /// Metres per pixel (pixels are square).
    pub fn metres_per_pixel(&self) -> f64 {
        self.side / f64::from(self.resolution)
    }

    /// Continuous pixel coordinates `(col, row)` of the floor point `(x, z)`.
    pub fn floor_to_pixel(&self, x: f64, z: f64) -> (f64, f64) {
        let m = self.metres_per_pixel();
        ((x - self.min_x) / m, (z - self.min_z) / m)
    }

    /// The floor point `(x, z)` at continuous pixel coordinates `(col, row)`.
    pub fn pixel_to_floor(&self, col: f64, row: f64) -> (f64, f64) {
        let m = self.metres_per_pixel();
        (self.min_x + col * m, self.min_z + row * m)
    }

    /// The floor point `(x, z)` at the centre of pixel `(col, row)`.
    pub fn pixel_centre_to_floor(&self, col: u32, row: u32) -> (f64, f64) {
        self.pixel_to_floor(f64::from(col) + 0.5, f64::from(row) + 0.5)
    }

    /// The pixel `(col, row)` that contains the floor point `(x, z)`, if it is in the image.
    pub fn floor_to_pixel_index(&self, x: f64, z: f64) -> Option<(u32, u32)> {
        let (c, r) = self.floor_to_pixel(x, z);
        let n = f64::from(self.resolution);
        ((0.0..n).contains(&c) && (0.0..n).contains(&r)).then(|| (c.floor() as u32, r.floor() as u32))
    }

    /// Centre of the region on the plan.
    pub(crate) fn centre(&self) -> (f64, f64) {
        (self.min_x + self.side / 2.0, self.min_z + self.side / 2.0)
    }
}

/// An orthonormal camera basis.
struct Basis {
    right: [f64; 3],
    up: [f64; 3],
    forward: [f64; 3],
}

fn ego_basis(camera: &EgoCamera) -> Basis {
    let (sy, cy) = camera.yaw.sin_cos();
    let (sp, cp) = camera.pitch.sin_cos();
    let forward = [cp * cy, -sp, -cp * sy];
    let right = [sy, 0.0, cy];
    // up = right × forward
    let up = [
        right[1] * forward[2] - right[2] * forward[1],
        right[2] * forward[0] - right[0] * forward[2],
        right[0] * forward[1] - right[1] * forward[0],
    ];
    Basis { right, up, forward }
}

fn focal_scale(camera: &EgoCamera) -> f64 {
    1.0 / (camera.horizontal_fov / 2.0).tan()
}

/// Where a world point appears in the egocentric image of `resolution` × `resolution` pixels:
/// continuous `(col, row)` and the view depth in metres, or `None` when it is behind the near
/// plane. The point may lie outside the image.
pub fn project_ego(camera: &EgoCamera, point: [f64; 3], resolution: u32) -> Option<(f64, f64, f64)> {
    let b = ego_basis(camera);
    let rel = [point[0] - camera.eye[0], point[1] - camera.eye[1], point[2] - camera.eye[2]];
    let dot = |a: [f64; 3]| a[0] * rel[0] + a[1] * rel[1] + a[2] * rel[2];
    let depth = dot(b.forward);
    if depth < EGO_NEAR {
        return None;
    }
    let f = focal_scale(camera);
    let (x, y) = (dot(b.right) * f / depth, dot(b.up) * f / depth);
    let n = f64::from(resolution);
    Some(((x + 1.0) / 2.0 * n, (1.0 - y) / 2.0 * n, depth))
}

/// The egocentric camera's view volume, for culling: a sphere it reports outside covers no
/// pixel of the image.
pub(crate) struct EgoFrustum {
    eye: [f64; 3],
    basis: Basis,
    focal: f64,
    /// Length of the side planes' normals, `sqrt(focal² + 1)`.
    side_norm: f64,
}

/// Added to every bounding radius: far more than the f32 rounding of the device's vertex
/// work, so that culling never removes a triangle that could touch a pixel.
const CULL_MARGIN: f64 = 0.01;

impl EgoFrustum {
    pub(crate) fn new(camera: &EgoCamera) -> Self {
        let focal = focal_scale(camera);
        Self { eye: camera.eye, basis: ego_basis(camera), focal, side_norm: (focal * focal + 1.0).sqrt() }
    }

    /// Whether the sphere at `centre` (world frame) of `radius` lies wholly outside one of the
    /// planes that bound the image (clip space |x| ≤ w, |y| ≤ w, and the near plane).
    pub(crate) fn excludes(&self, centre: [f64; 3], radius: f64) -> bool {
        let rel = [centre[0] - self.eye[0], centre[1] - self.eye[1], centre[2] - self.eye[2]];
        let dot = |a: [f64; 3]| a[0] * rel[0] + a[1] * rel[1] + a[2] * rel[2];
        let r = radius + CULL_MARGIN;
        let d = dot(self.basis.forward);
        let (x, y) = (dot(self.basis.right) * self.focal, dot(self.basis.up) * self.focal);
        let side = r * self.side_norm;
        d + r < EGO_NEAR || x - d > side || -x - d > side || y - d > side || -y - d > side
    }
}

fn v4(v: [f64; 3], w: f64) -> [f32; 4] {
    [v[0] as f32, v[1] as f32, v[2] as f32, w as f32]
}

/// Uniforms of the egocentric camera.
pub(crate) fn ego_view(camera: &EgoCamera) -> GpuView {
    let b = ego_basis(camera);
    let f = focal_scale(camera);
    GpuView {
        eye: v4(camera.eye, 1.0),
        right: v4(b.right, f),
        up: v4(b.up, f),
        forward: v4(b.forward, 0.0),
        // Reverse Z with an infinite far plane: z_ndc = near / d.
        depth_map: [0.0, EGO_NEAR as f32, 1.0, 0.0],
        poses: [[1.0, 0.0, 0.0, 0.0]; MAX_POSE_SLOTS],
        tile: [0; 4],
    }
}

/// Uniforms of the top-down camera over `frame`, for geometry no higher than `max_height`.
pub(crate) fn top_down_view(frame: &TopDownFrame, max_height: f64) -> GpuView {
    let (cx, cz) = frame.centre();
    let top = max_height.max(0.0) + 1.0;
    let range = top + 1.0;
    let scale = 2.0 / frame.side;
    GpuView {
        eye: v4([cx, top, cz], 1.0),
        right: v4([1.0, 0.0, 0.0], scale),
        up: v4([0.0, 0.0, -1.0], scale),
        forward: v4([0.0, -1.0, 0.0], 0.0),
        // Reverse Z: z_ndc = 1 − d / range.
        depth_map: [(-1.0 / range) as f32, 1.0, 0.0, 1.0],
        poses: [[1.0, 0.0, 0.0, 0.0]; MAX_POSE_SLOTS],
        tile: [0; 4],
    }
}
