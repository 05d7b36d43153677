//! Triangle meshes built from esrp-core shapes, their colours and their segmentation labels.
//!
//! A scene becomes one indexed triangle list ([`SceneMesh`]) with flat normals: the floor
//! (ear-clipped polygon), the wall pieces (boxes), the fixed objects (placed in the world), and
//! the movable objects in their own frames, each vertex tagged with the pose slot that places it
//! on the GPU (slot 0: static geometry, slot `1 + i`: movable object `i`). Colours and labels are
//! baked into the vertices because they never change within a scene.

use std::collections::HashMap;

use esrp_core::parry3d::math::Vector;
use esrp_core::parry3d::transformation::try_convex_hull;
use esrp_core::{CompiledScene, MovableCategory, ObjectPose, Part, Shape, WallPieceKind};

use crate::error::RenderError;
use crate::gpu::GpuVertex;

/// Number of sides of the prism that stands for a cylinder.
pub const CYLINDER_SIDES: usize = 12;

/// An RGB colour with components in `[0, 1]`, before lighting.
pub type Rgb = [f32; 3];

/// Colour of the floor (warm beige).
pub const FLOOR_COLOUR: Rgb = [0.72, 0.66, 0.56];
/// Colour of the walls (off-white).
pub const WALL_COLOUR: Rgb = [0.86, 0.85, 0.81];
/// Colour of the closed door leaves (muted brown).
pub const DOOR_COLOUR: Rgb = [0.52, 0.43, 0.36];
/// Base colour of fixed furniture (cool grey); each piece is shaded slightly by its index.
pub const FIXED_COLOUR: Rgb = [0.50, 0.51, 0.55];
/// Colour where nothing is drawn: outside the room and through windows (dark slate).
pub const BACKGROUND_COLOUR: Rgb = [0.10, 0.11, 0.13];

/// The fixed colour of a movable category (SPEC §4), before the per-instance tint.
pub fn category_colour(category: MovableCategory) -> Rgb {
    match category {
        MovableCategory::CabinetShelfDesk => [0.16, 0.42, 0.88],
        MovableCategory::Chair => [0.88, 0.20, 0.16],
        MovableCategory::Sofa => [0.18, 0.70, 0.26],
        MovableCategory::PierStool => [0.98, 0.72, 0.08],
        MovableCategory::Others => [0.78, 0.22, 0.86],
    }
}

/// The colour of movable object `index` of category `category`: the category colour with a
/// small deterministic brightness tint from the object's index, so that two chairs differ a
/// little but stay recognisably chairs.
pub fn movable_colour(category: MovableCategory, index: usize) -> Rgb {
    const TINTS: [f32; 8] = [1.0, 0.88, 1.12, 0.94, 1.06, 0.84, 0.97, 1.16];
    let tint = TINTS[index % TINTS.len()];
    category_colour(category).map(|c| (c * tint).clamp(0.0, 1.0))
}

/// The colour of fixed object `index`: [`FIXED_COLOUR`] a little lighter or darker by index.
pub fn fixed_colour(index: usize) -> Rgb {
    const SHADES: [f32; 4] = [1.0, 0.88, 1.10, 0.94];
    FIXED_COLOUR.map(|c| c * SHADES[index % SHADES.len()])
}

/// What a pixel of the segmentation image shows. Its `u32` encoding is [`SegmentLabel::id`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SegmentLabel {
    /// Nothing: outside the room, or through a window (id 0).
    Background,
    /// The floor (id 1).
    Floor,
    /// A wall (id 2).
    Wall,
    /// A closed door leaf (id 3).
    Door,
    /// Fixed object `i` of `fixed_objects` (id `0x1_0000 + i`).
    Fixed(usize),
    /// Movable object `i` of `movable_objects` (id `0x2_0000 + i`).
    Movable(usize),
}

const FIXED_BASE: u32 = 0x1_0000;
const MOVABLE_BASE: u32 = 0x2_0000;

impl SegmentLabel {
    /// The label's id in segmentation images.
    pub fn id(self) -> u32 {
        match self {
            Self::Background => 0,
            Self::Floor => 1,
            Self::Wall => 2,
            Self::Door => 3,
            Self::Fixed(i) => FIXED_BASE + i as u32,
            Self::Movable(i) => MOVABLE_BASE + i as u32,
        }
    }

    /// The label of a segmentation id, or `None` for an id no label has.
    pub fn from_id(id: u32) -> Option<Self> {
        match id {
            0 => Some(Self::Background),
            1 => Some(Self::Floor),
            2 => Some(Self::Wall),
            3 => Some(Self::Door),
            FIXED_BASE..MOVABLE_BASE => Some(Self::Fixed((id - FIXED_BASE) as usize)),
            MOVABLE_BASE..0x3_0000 => Some(Self::Movable((id - MOVABLE_BASE) as usize)),
            _ => None,
        }
    }
}

/// A run of a scene mesh's indices that belongs to one piece (the floor, a wall piece, an
/// object), with a sphere that bounds it, for culling pieces a view cannot see.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct MeshPart {
    /// First index of the run.
    pub first: u32,
    /// Number of indices.
    pub count: u32,
    /// Pose slot of its vertices: 0 for the world frame, `1 + i` for movable object `i`.
    pub slot: u32,
    /// Centre of the bounding sphere, in the slot's frame.
    pub centre: [f64; 3],
    /// Its radius, metres.
    pub radius: f64,
}

/// A scene as one indexed triangle list, ready for upload.
#[derive(Clone, Debug, Default)]
pub struct SceneMesh {
    pub(crate) vertices: Vec<GpuVertex>,
    pub(crate) indices: Vec<u32>,
    /// Consecutive runs of `indices`, one per piece, in order.
    pub(crate) parts: Vec<MeshPart>,
    /// Highest point of any geometry, metres (for the top-down camera).
    pub(crate) max_height: f64,
}

impl SceneMesh {
    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Number of distinct vertices.
    pub fn vertex_count(&self) -> usize {
        self.vertices.len()
    }
}

type P3 = [f64; 3];

fn sub(a: P3, b: P3) -> P3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: P3, b: P3) -> P3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn dot(a: P3, b: P3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Rotation by `yaw` about +y, then translation (SPEC §1: local +x goes to (cos, 0, −sin)).
fn place(p: P3, offset: P3, yaw: f64) -> P3 {
    let (s, c) = yaw.sin_cos();
    [c * p[0] + s * p[2] + offset[0], p[1] + offset[1], -s * p[0] + c * p[2] + offset[2]]
}

fn place_pose(p: P3, pose: &ObjectPose) -> P3 {
    place(p, [pose.x, 0.0, pose.z], pose.yaw)
}

/// Triangles of one convex or mesh part, before orientation fixes.
struct Triangles(Vec<[P3; 3]>);

impl Triangles {
    /// Flips every triangle whose normal points towards `inside`, so that all face outwards.
    fn orient_outward(mut self, inside: P3) -> Self {
        for t in &mut self.0 {
            let n = cross(sub(t[1], t[0]), sub(t[2], t[0]));
            let centre = [
                (t[0][0] + t[1][0] + t[2][0]) / 3.0,
                (t[0][1] + t[1][1] + t[2][1]) / 3.0,
                (t[0][2] + t[1][2] + t[2][2]) / 3.0,
            ];
            if dot(n, sub(centre, inside)) < 0.0 {
                t.swap(1, 2);
            }
        }
        self
    }

    fn map(mut self, f: impl Fn(P3) -> P3) -> Self {
        for t in &mut self.0 {
            *t = t.map(&f);
        }
        self
    }
}

/// The 12 triangles of a box centred at the origin.
fn box_triangles(h: P3) -> Triangles {
    let corner = |i: usize| {
        [
            if i & 1 == 0 { -h[0] } else { h[0] },
            if i & 2 == 0 { -h[1] } else { h[1] },
            if i & 4 == 0 { -h[2] } else { h[2] },
        ]
    };
    // Faces as corner quads; orientation is fixed afterwards.
    const FACES: [[usize; 4]; 6] = [[0, 2, 6, 4], [1, 5, 7, 3], [0, 4, 5, 1], [2, 3, 7, 6], [0, 1, 3, 2], [4, 6, 7, 5]];
    let mut out = Vec::with_capacity(12);
    for f in FACES {
        out.push([corner(f[0]), corner(f[1]), corner(f[2])]);
        out.push([corner(f[0]), corner(f[2]), corner(f[3])]);
    }
    Triangles(out).orient_outward([0.0; 3])
}

/// A vertical prism with [`CYLINDER_SIDES`] sides standing for a cylinder centred at the origin.
fn cylinder_triangles(radius: f64, half_height: f64) -> Triangles {
    let ring: Vec<(f64, f64)> = (0..CYLINDER_SIDES)
        .map(|i| {
            let a = std::f64::consts::TAU * (i as f64 + 0.5) / CYLINDER_SIDES as f64;
            (radius * a.cos(), radius * a.sin())
        })
        .collect();
    let mut out = Vec::with_capacity(4 * CYLINDER_SIDES);
    for i in 0..CYLINDER_SIDES {
        let (x0, z0) = ring[i];
        let (x1, z1) = ring[(i + 1) % CYLINDER_SIDES];
        let (b0, b1, t0, t1) =
            ([x0, -half_height, z0], [x1, -half_height, z1], [x0, half_height, z0], [x1, half_height, z1]);
        out.push([b0, b1, t1]);
        out.push([b0, t1, t0]);
        out.push([[0.0, half_height, 0.0], t0, t1]);
        out.push([[0.0, -half_height, 0.0], b1, b0]);
    }
    Triangles(out).orient_outward([0.0; 3])
}

fn hull_triangles(points: &[[f64; 3]]) -> Result<Triangles, String> {
    let input: Vec<Vector> = points.iter().map(|p| Vector::new(p[0], p[1], p[2])).collect();
    let (vertices, faces) = try_convex_hull(&input).map_err(|e| format!("{e:?}"))?;
    let v = |i: u32| {
        let p = vertices[i as usize];
        [p.x, p.y, p.z]
    };
    let n = vertices.len().max(1) as f64;
    let centroid = vertices.iter().fold([0.0; 3], |a, p| [a[0] + p.x / n, a[1] + p.y / n, a[2] + p.z / n]);
    Ok(Triangles(faces.iter().map(|f| [v(f[0]), v(f[1]), v(f[2])]).collect()).orient_outward(centroid))
}

/// The triangles of a shape in its object's frame.
fn shape_triangles(shape: &Shape) -> Result<Triangles, String> {
    match shape {
        Shape::Parts(parts) => {
            let mut all = Vec::new();
            for part in parts {
                let (offset, yaw) = part.placement();
                let local = match part {
                    Part::Box { half_extents, .. } => box_triangles(*half_extents),
                    Part::Cylinder { radius, half_height, .. } => cylinder_triangles(*radius, *half_height),
                    Part::ConvexHull { points, .. } => hull_triangles(points)?,
                };
                all.extend(local.map(|p| place(p, offset, yaw)).0);
            }
            Ok(Triangles(all))
        }
        Shape::Mesh(mesh) => {
            let mut all = Vec::with_capacity(mesh.triangles.len());
            for t in &mesh.triangles {
                let get =
                    |i: u32| mesh.vertices.get(i as usize).copied().ok_or(format!("vertex index {i} out of range"));
                all.push([get(t[0])?, get(t[1])?, get(t[2])?]);
            }
            Ok(Triangles(all))
        }
    }
}

/// Ear clipping of a simple polygon in the plan; returns triangles of indices, counter-clockwise
/// in `(x, z)` as given (the caller orients them).
fn triangulate_polygon(points: &[[f64; 2]]) -> Vec<[usize; 3]> {
    let n = points.len();
    if n < 3 {
        return Vec::new();
    }
    let area2: f64 = (0..n)
        .map(|i| {
            let (a, b) = (points[i], points[(i + 1) % n]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    let mut remaining: Vec<usize> = if area2 >= 0.0 { (0..n).collect() } else { (0..n).rev().collect() };
    let orient = |a: [f64; 2], b: [f64; 2], c: [f64; 2]| (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
    let mut out = Vec::with_capacity(n - 2);
    let mut guard = 0;
    while remaining.len() > 3 && guard < 10 * n * n {
        guard += 1;
        let m = remaining.len();
        let mut clipped = false;
        for i in 0..m {
            let (ia, ib, ic) = (remaining[(i + m - 1) % m], remaining[i], remaining[(i + 1) % m]);
            let (a, b, c) = (points[ia], points[ib], points[ic]);
            if orient(a, b, c) <= 1e-12 {
                continue;
            }
            let contains = remaining.iter().any(|&j| {
                if j == ia || j == ib || j == ic {
                    return false;
                }
                let p = points[j];
                orient(a, b, p) >= 0.0 && orient(b, c, p) >= 0.0 && orient(c, a, p) >= 0.0
            });
            if !contains {
                out.push([ia, ib, ic]);
                remaining.remove(i);
                clipped = true;
                break;
            }
        }
        if !clipped {
            // Degenerate input (collinear runs, touching edges): fall back to a fan.
            break;
        }
    }
    for i in 1..remaining.len().saturating_sub(1) {
        out.push([remaining[0], remaining[i], remaining[i + 1]]);
    }
    out
}

/// Builds the indexed mesh, merging identical vertices.
struct MeshBuilder {
    mesh: SceneMesh,
    lookup: HashMap<[u32; 9], u32>,
}

impl MeshBuilder {
    fn add(&mut self, triangles: &Triangles, slot: u32, colour: Rgb, segment: SegmentLabel) {
        let packed = u32::from_le_bytes([
            (colour[0].clamp(0.0, 1.0) * 255.0).round() as u8,
            (colour[1].clamp(0.0, 1.0) * 255.0).round() as u8,
            (colour[2].clamp(0.0, 1.0) * 255.0).round() as u8,
            255,
        ]);
        let segment = segment.id();
        let first = self.mesh.indices.len() as u32;
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for t in &triangles.0 {
            let n = cross(sub(t[1], t[0]), sub(t[2], t[0]));
            let len = dot(n, n).sqrt();
            if len.is_nan() || len <= 1e-12 {
                continue;
            }
            let normal = n.map(|c| (c / len) as f32);
            for p in t {
                for k in 0..3 {
                    lo[k] = lo[k].min(p[k]);
                    hi[k] = hi[k].max(p[k]);
                }
                self.mesh.max_height = self.mesh.max_height.max(p[1]);
                let vertex = GpuVertex { position: p.map(|c| c as f32), slot, normal, colour: packed, segment };
                let key: [u32; 9] = bytemuck::cast(vertex);
                let next = self.mesh.vertices.len() as u32;
                let index = *self.lookup.entry(key).or_insert(next);
                if index == next {
                    self.mesh.vertices.push(vertex);
                }
                self.mesh.indices.push(index);
            }
        }
        let count = self.mesh.indices.len() as u32 - first;
        if count > 0 {
            let centre = [0, 1, 2].map(|k| (lo[k] + hi[k]) / 2.0);
            let radius = [0, 1, 2].map(|k| (hi[k] - lo[k]) / 2.0).iter().map(|h| h * h).sum::<f64>().sqrt();
            self.mesh.parts.push(MeshPart { first, count, slot, centre, radius });
        }
    }
}

/// Builds the mesh of a compiled scene: floor, walls and doors, fixed objects in the world
/// frame (slot 0) and movable object `i` in its own frame (slot `1 + i`).
pub fn build_scene_mesh(compiled: &CompiledScene) -> Result<SceneMesh, RenderError> {
    let scene = compiled.scene();
    let mut builder = MeshBuilder { mesh: SceneMesh::default(), lookup: HashMap::new() };

    let floor = &scene.room.floor;
    let floor_triangles =
        Triangles(triangulate_polygon(floor).into_iter().map(|t| t.map(|i| [floor[i][0], 0.0, floor[i][1]])).collect())
            .orient_outward([0.0, -1.0e9, 0.0]);
    builder.add(&floor_triangles, 0, FLOOR_COLOUR, SegmentLabel::Floor);

    for piece in compiled.wall_pieces() {
        let triangles = box_triangles(piece.half_extents).map(|p| place(p, piece.center, piece.yaw));
        let (colour, label) = match piece.kind {
            WallPieceKind::Wall => (WALL_COLOUR, SegmentLabel::Wall),
            WallPieceKind::Door => (DOOR_COLOUR, SegmentLabel::Door),
        };
        builder.add(&triangles, 0, colour, label);
    }

    for (i, object) in scene.fixed_objects.iter().enumerate() {
        let triangles = shape_triangles(&object.shape)
            .map_err(|reason| RenderError::InvalidShape { object: object.id.clone(), reason })?
            .map(|p| place_pose(p, &object.pose));
        builder.add(&triangles, 0, fixed_colour(i), SegmentLabel::Fixed(i));
    }

    for (i, object) in scene.movable_objects.iter().enumerate() {
        let triangles = shape_triangles(&object.shape)
            .map_err(|reason| RenderError::InvalidShape { object: object.id.clone(), reason })?;
        builder.add(&triangles, 1 + i as u32, movable_colour(object.category, i), SegmentLabel::Movable(i));
    }
    Ok(builder.mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn l_shape_triangulates_to_its_area() {
        let l = [[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [2.0, 2.0], [2.0, 4.0], [0.0, 4.0]];
        for polygon in [l.to_vec(), l.iter().rev().copied().collect()] {
            let tris = triangulate_polygon(&polygon);
            assert_eq!(tris.len(), 4);
            let area: f64 = tris
                .iter()
                .map(|t| {
                    let (a, b, c) = (polygon[t[0]], polygon[t[1]], polygon[t[2]]);
                    ((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])).abs() / 2.0
                })
                .sum();
            assert!((area - 12.0).abs() < 1e-9, "area {area}");
        }
    }

    #[test]
    fn segment_ids_round_trip() {
        for label in [
            SegmentLabel::Background,
            SegmentLabel::Floor,
            SegmentLabel::Wall,
            SegmentLabel::Door,
            SegmentLabel::Fixed(7),
            SegmentLabel::Movable(5),
        ] {
            assert_eq!(SegmentLabel::from_id(label.id()), Some(label));
        }
    }
}
