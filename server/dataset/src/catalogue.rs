//! The furniture catalogue: low-poly models built from boxes, cylinders and convex hulls, with
//! real-world sizes and several variants per kind.
//!
//! Every model stands on the floor (y = 0) with its footprint centred on its origin and its
//! **front facing local +x**; "against a wall" means its back (local −x) towards the wall.
//! Widths run along local z, depths along local x.
//!
//! Movable models carry their category (SPEC §7: carried by the agent, so no larger than about
//! its reach — at most 1.2 m across and 1.3 m high); fixed models have none.

use std::sync::OnceLock;

use esrp_core::{MovableCategory, Part};

/// What a model is, for the layout rules.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Kind {
    /// Beds (fixed).
    Bed,
    /// Wardrobes (fixed).
    Wardrobe,
    /// Large sofas (fixed).
    Sofa,
    /// Dining tables (fixed).
    DiningTable,
    /// Kitchen counters and fridges (fixed).
    Counter,
    /// TV stands (fixed).
    TvStand,
    /// Tall bookshelves (fixed).
    Bookcase,
    /// Bathtubs, vanities, toilets (fixed).
    Bath,
    /// Large desks (fixed).
    LargeDesk,
    /// Nightstands (movable cabinet).
    Nightstand,
    /// Low cabinets, dressers, sideboards (movable cabinet).
    Cabinet,
    /// Small shelves (movable).
    Shelf,
    /// Small desks (movable).
    Desk,
    /// Chairs (movable).
    Chair,
    /// Armchairs and loveseats (movable sofa).
    Armchair,
    /// Stools and ottomans (movable).
    Stool,
    /// Side and coffee tables (movable other).
    SideTable,
    /// Potted plants (movable other).
    Plant,
    /// Floor lamps (movable other).
    Lamp,
}

/// One catalogue model.
#[derive(Clone, Debug)]
pub struct Model {
    /// Unique name, e.g. `chair_dining_a`.
    pub name: &'static str,
    /// What it is.
    pub kind: Kind,
    /// The fixed-object category written into scenes (`bed`, `wardrobe`, ...).
    pub category: &'static str,
    /// Its category when movable; `None` for fixed furniture.
    pub movable: Option<MovableCategory>,
    /// Convex parts in the model frame.
    pub parts: Vec<Part>,
    /// Depth (local x), height and width (local z) of its bounding box, metres.
    pub size: [f64; 3],
}

impl Model {
    /// Depth along local x (front to back).
    pub fn depth(&self) -> f64 {
        self.size[0]
    }

    /// Width along local z (side to side).
    pub fn width(&self) -> f64 {
        self.size[2]
    }

    /// Number of triangles its parts draw as (boxes 12, cylinders 48, hulls about 2 per point).
    pub fn triangle_estimate(&self) -> usize {
        self.parts
            .iter()
            .map(|p| match p {
                Part::Box { .. } => 12,
                Part::Cylinder { .. } => 48,
                Part::ConvexHull { points, .. } => 2 * points.len(),
            })
            .sum()
    }
}

/// A box of full size `(dx, dy, dz)` centred at `(x, z)` with its bottom at `y0`.
fn bx(dx: f64, dy: f64, dz: f64, x: f64, y0: f64, z: f64) -> Part {
    Part::Box { half_extents: [dx / 2.0, dy / 2.0, dz / 2.0], offset: [x, y0 + dy / 2.0, z], yaw: 0.0 }
}

/// A vertical cylinder of radius `r` and height `h` centred at `(x, z)`, bottom at `y0`.
fn cyl(r: f64, h: f64, x: f64, y0: f64, z: f64) -> Part {
    Part::Cylinder { radius: r, half_height: h / 2.0, offset: [x, y0 + h / 2.0, z], yaw: 0.0 }
}

/// Four square legs of side `s` and height `h` at the corners of a `depth × width` top.
fn legs(depth: f64, width: f64, h: f64, s: f64) -> Vec<Part> {
    let (x, z) = (depth / 2.0 - s / 2.0, width / 2.0 - s / 2.0);
    [(-x, -z), (x, -z), (x, z), (-x, z)].iter().map(|&(px, pz)| bx(s, h, s, px, 0.0, pz)).collect()
}

/// An octahedron-like hull of radius `r`, height `h` above `y0`: foliage, lamp shades.
fn blob(r: f64, h: f64, y0: f64) -> Part {
    let mid = y0 + h / 2.0;
    let d = r * std::f64::consts::FRAC_1_SQRT_2;
    Part::ConvexHull {
        points: vec![
            [r, mid, 0.0],
            [-r, mid, 0.0],
            [0.0, mid, r],
            [0.0, mid, -r],
            [d, mid + h * 0.25, d],
            [-d, mid + h * 0.25, -d],
            [d, mid - h * 0.25, -d],
            [-d, mid - h * 0.25, d],
            [0.0, y0 + h, 0.0],
            [0.0, y0, 0.0],
        ],
        offset: [0.0; 3],
        yaw: 0.0,
    }
}

fn model(
    name: &'static str,
    kind: Kind,
    category: &'static str,
    movable: Option<MovableCategory>,
    size: [f64; 3],
    parts: Vec<Part>,
) -> Model {
    Model { name, kind, category, movable, parts, size }
}

fn bed(name: &'static str, length: f64, width: f64) -> Model {
    // Head against the wall: the headboard is at the back (−x), the foot at +x.
    model(
        name,
        Kind::Bed,
        "bed",
        None,
        [length, 1.0, width],
        vec![
            bx(length - 0.08, 0.3, width, 0.04, 0.0, 0.0),
            bx(length - 0.12, 0.22, width - 0.06, 0.05, 0.3, 0.0),
            bx(0.08, 1.0, width, -length / 2.0 + 0.04, 0.0, 0.0),
            bx(0.5, 0.12, width - 0.3, -length / 2.0 + 0.4, 0.52, 0.0),
        ],
    )
}

fn wardrobe(name: &'static str, width: f64, height: f64) -> Model {
    model(
        name,
        Kind::Wardrobe,
        "wardrobe",
        None,
        [0.6, height, width],
        vec![bx(0.58, height - 0.08, width, -0.01, 0.08, 0.0), bx(0.5, 0.08, width - 0.1, -0.05, 0.0, 0.0)],
    )
}

fn sofa(name: &'static str, width: f64, fixed: bool) -> Model {
    let depth = 0.9;
    let parts = vec![
        bx(depth - 0.1, 0.42, width - 0.36, 0.05, 0.0, 0.0),
        bx(0.2, 0.85, width, -depth / 2.0 + 0.1, 0.0, 0.0),
        bx(depth, 0.62, 0.18, 0.0, 0.0, width / 2.0 - 0.09),
        bx(depth, 0.62, 0.18, 0.0, 0.0, -width / 2.0 + 0.09),
    ];
    if fixed {
        model(name, Kind::Sofa, "sofa", None, [depth, 0.85, width], parts)
    } else {
        model(name, Kind::Armchair, "armchair", Some(MovableCategory::Sofa), [depth, 0.85, width], parts)
    }
}

fn table(name: &'static str, kind: Kind, movable: Option<MovableCategory>, size: [f64; 3], leg: f64) -> Model {
    let [depth, height, width] = size;
    let mut parts = vec![bx(depth, 0.04, width, 0.0, height - 0.04, 0.0)];
    parts.extend(legs(depth - 0.04, width - 0.04, height - 0.04, leg));
    let category = match kind {
        Kind::DiningTable => "dining_table",
        Kind::LargeDesk | Kind::Desk => "desk",
        _ => "table",
    };
    model(name, kind, category, movable, size, parts)
}

fn chair(name: &'static str, seat: f64, back_height: f64, solid_back: bool) -> Model {
    let mut parts = vec![bx(seat, 0.05, seat, 0.0, 0.42, 0.0)];
    parts.extend(legs(seat, seat, 0.42, 0.035));
    if solid_back {
        parts.push(bx(0.04, back_height, seat, -seat / 2.0 + 0.02, 0.47, 0.0));
    } else {
        parts.push(bx(0.035, back_height, 0.035, -seat / 2.0 + 0.0175, 0.47, seat / 2.0 - 0.0175));
        parts.push(bx(0.035, back_height, 0.035, -seat / 2.0 + 0.0175, 0.47, -seat / 2.0 + 0.0175));
        parts.push(bx(0.035, 0.14, seat, -seat / 2.0 + 0.0175, 0.47 + back_height - 0.14, 0.0));
    }
    model(name, Kind::Chair, "chair", Some(MovableCategory::Chair), [seat, 0.47 + back_height, seat], parts)
}

fn cabinet(name: &'static str, kind: Kind, size: [f64; 3], on_legs: bool) -> Model {
    let [depth, height, width] = size;
    let mut parts = Vec::new();
    if on_legs {
        parts.push(bx(depth, height - 0.12, width, 0.0, 0.12, 0.0));
        parts.extend(legs(depth - 0.04, width - 0.04, 0.12, 0.04));
    } else {
        parts.push(bx(depth - 0.02, height - 0.03, width, -0.01, 0.0, 0.0));
        parts.push(bx(depth, 0.03, width + 0.02, 0.0, height - 0.03, 0.0));
    }
    let category = match kind {
        Kind::Nightstand => "nightstand",
        Kind::Bath => "vanity",
        Kind::TvStand => "tv_stand",
        Kind::Counter => "kitchen_counter",
        _ => "cabinet",
    };
    let movable = matches!(kind, Kind::Nightstand | Kind::Cabinet).then_some(MovableCategory::CabinetShelfDesk);
    model(name, kind, category, movable, size, parts)
}

fn shelf(name: &'static str, kind: Kind, size: [f64; 3], shelves: usize) -> Model {
    let [depth, height, width] = size;
    let mut parts = vec![
        bx(depth, height, 0.03, 0.0, 0.0, width / 2.0 - 0.015),
        bx(depth, height, 0.03, 0.0, 0.0, -width / 2.0 + 0.015),
        bx(0.02, height, width - 0.06, -depth / 2.0 + 0.01, 0.0, 0.0),
    ];
    for i in 0..=shelves {
        let y = (height - 0.03) * i as f64 / shelves as f64;
        parts.push(bx(depth - 0.02, 0.03, width - 0.06, 0.01, y, 0.0));
    }
    let movable = (kind == Kind::Shelf).then_some(MovableCategory::CabinetShelfDesk);
    let category = if kind == Kind::Shelf { "shelf" } else { "bookcase" };
    model(name, kind, category, movable, size, parts)
}

fn stool(name: &'static str, round: bool, height: f64, size: f64) -> Model {
    let parts = if round {
        vec![
            cyl(size / 2.0, 0.05, 0.0, height - 0.05, 0.0),
            cyl(0.03, height - 0.05, 0.0, 0.0, 0.0),
            cyl(size / 2.5, 0.03, 0.0, 0.0, 0.0),
        ]
    } else {
        let mut p = vec![bx(size, 0.05, size, 0.0, height - 0.05, 0.0)];
        p.extend(legs(size, size, height - 0.05, 0.03));
        p
    };
    model(name, Kind::Stool, "stool", Some(MovableCategory::PierStool), [size, height, size], parts)
}

fn plant(name: &'static str, pot: f64, height: f64) -> Model {
    let pot_height = (height * 0.3).min(0.45);
    model(
        name,
        Kind::Plant,
        "plant",
        Some(MovableCategory::Others),
        [pot * 2.4, height, pot * 2.4],
        vec![cyl(pot, pot_height, 0.0, 0.0, 0.0), blob(pot * 1.2, height - pot_height, pot_height)],
    )
}

fn lamp(name: &'static str, height: f64, shade: f64) -> Model {
    model(
        name,
        Kind::Lamp,
        "lamp",
        Some(MovableCategory::Others),
        [shade * 2.0, height, shade * 2.0],
        vec![
            cyl(0.15, 0.03, 0.0, 0.0, 0.0),
            cyl(0.015, height - 0.3, 0.0, 0.03, 0.0),
            cyl(shade, 0.3, 0.0, height - 0.3, 0.0),
        ],
    )
}

/// The catalogue, one model per line. It stays one long list on purpose: it is data, read as a
/// table (fixed furniture, then the movable categories), and its order is the models' ids.
fn build() -> Vec<Model> {
    use Kind::*;
    use MovableCategory as M;
    vec![
        // Fixed furniture.
        bed("bed_single", 2.0, 1.0),
        bed("bed_double", 2.1, 1.5),
        bed("bed_queen", 2.1, 1.7),
        wardrobe("wardrobe_narrow", 1.0, 2.0),
        wardrobe("wardrobe_double", 1.6, 2.2),
        sofa("sofa_three_seat", 2.1, true),
        sofa("sofa_two_seat_large", 1.7, true),
        table("dining_table_four", DiningTable, None, [0.85, 0.75, 1.3], 0.06),
        table("dining_table_six", DiningTable, None, [0.95, 0.75, 1.8], 0.07),
        table("desk_large", LargeDesk, None, [0.7, 0.75, 1.5], 0.05),
        cabinet("kitchen_counter_long", Counter, [0.62, 0.9, 2.4], false),
        cabinet("kitchen_counter_short", Counter, [0.62, 0.9, 1.2], false),
        model("fridge", Counter, "fridge", None, [0.7, 1.8, 0.7], vec![bx(0.7, 1.8, 0.7, 0.0, 0.0, 0.0)]),
        model(
            "tv_stand_low",
            TvStand,
            "tv_stand",
            None,
            [0.45, 1.15, 1.6],
            vec![
                bx(0.45, 0.5, 1.6, 0.0, 0.0, 0.0),
                bx(0.08, 0.6, 1.2, -0.1, 0.55, 0.0),
                bx(0.2, 0.05, 0.3, -0.1, 0.5, 0.0),
            ],
        ),
        cabinet("tv_stand_cabinet", TvStand, [0.42, 0.6, 1.8], true),
        shelf("bookcase_tall", Bookcase, [0.35, 2.0, 1.2], 5),
        shelf("bookcase_wide", Bookcase, [0.4, 1.8, 1.6], 4),
        model(
            "bathtub",
            Bath,
            "bathtub",
            None,
            [0.75, 0.58, 1.6],
            vec![
                bx(0.75, 0.12, 1.6, 0.0, 0.0, 0.0),
                bx(0.08, 0.46, 1.6, -0.335, 0.12, 0.0),
                bx(0.08, 0.46, 1.6, 0.335, 0.12, 0.0),
                bx(0.59, 0.46, 0.08, 0.0, 0.12, 0.76),
                bx(0.59, 0.46, 0.08, 0.0, 0.12, -0.76),
            ],
        ),
        cabinet("vanity", Bath, [0.5, 0.85, 0.9], false),
        model(
            "toilet",
            Bath,
            "toilet",
            None,
            [0.7, 0.8, 0.4],
            vec![bx(0.2, 0.8, 0.4, -0.25, 0.0, 0.0), cyl(0.19, 0.42, 0.08, 0.0, 0.0)],
        ),
        // Movable: cabinets, shelves and desks.
        cabinet("nightstand_block", Nightstand, [0.4, 0.55, 0.45], false),
        cabinet("nightstand_legs", Nightstand, [0.42, 0.6, 0.5], true),
        cabinet("cabinet_low", Cabinet, [0.45, 0.8, 0.8], false),
        cabinet("dresser", Cabinet, [0.5, 0.85, 1.0], true),
        cabinet("sideboard_small", Cabinet, [0.45, 0.75, 1.1], true),
        cabinet("cabinet_tall_narrow", Cabinet, [0.4, 1.2, 0.5], false),
        shelf("shelf_low", Shelf, [0.3, 0.9, 0.8], 3),
        shelf("shelf_cube", Shelf, [0.35, 1.1, 0.75], 3),
        table("desk_small", Desk, Some(M::CabinetShelfDesk), [0.55, 0.75, 1.0], 0.04),
        table("desk_writing", Desk, Some(M::CabinetShelfDesk), [0.6, 0.75, 1.15], 0.05),
        // Movable: chairs.
        chair("chair_dining_slats", 0.44, 0.45, false),
        chair("chair_dining_solid", 0.46, 0.42, true),
        chair("chair_side_low", 0.42, 0.35, true),
        model(
            "chair_office",
            Chair,
            "chair",
            Some(M::Chair),
            [0.55, 0.95, 0.55],
            vec![
                cyl(0.27, 0.05, 0.0, 0.0, 0.0),
                cyl(0.03, 0.4, 0.0, 0.05, 0.0),
                bx(0.48, 0.06, 0.48, 0.0, 0.45, 0.0),
                bx(0.05, 0.45, 0.42, -0.23, 0.5, 0.0),
            ],
        ),
        // Movable: armchairs and loveseats.
        sofa("armchair_boxy", 0.85, false),
        sofa("armchair_wide", 0.95, false),
        sofa("loveseat_compact", 1.2, false),
        model(
            "armchair_round",
            Armchair,
            "armchair",
            Some(M::Sofa),
            [0.8, 0.8, 0.8],
            vec![cyl(0.4, 0.42, 0.0, 0.0, 0.0), bx(0.18, 0.38, 0.7, -0.31, 0.42, 0.0)],
        ),
        // Movable: piers and stools.
        stool("stool_round", true, 0.45, 0.36),
        stool("stool_bar", true, 0.7, 0.38),
        stool("stool_square", false, 0.45, 0.38),
        model(
            "ottoman_cube",
            Stool,
            "ottoman",
            Some(M::PierStool),
            [0.5, 0.42, 0.5],
            vec![bx(0.5, 0.42, 0.5, 0.0, 0.0, 0.0)],
        ),
        // Movable: others.
        model(
            "side_table_round",
            SideTable,
            "side_table",
            Some(M::Others),
            [0.5, 0.55, 0.5],
            vec![cyl(0.25, 0.03, 0.0, 0.52, 0.0), cyl(0.03, 0.52, 0.0, 0.0, 0.0), cyl(0.16, 0.03, 0.0, 0.0, 0.0)],
        ),
        table("side_table_square", SideTable, Some(M::Others), [0.45, 0.55, 0.45], 0.035),
        table("coffee_table", SideTable, Some(M::Others), [0.55, 0.42, 1.0], 0.05),
        plant("plant_small", 0.14, 0.7),
        plant("plant_tall", 0.18, 1.25),
        lamp("lamp_floor", 1.3, 0.2),
    ]
}

/// Shifts a model's parts so that its bounding box is centred on the origin in x and z, and
/// sets `size` to that box: placement then never trusts a hand-typed size.
fn centred(mut m: Model) -> Model {
    let (mut lo, mut hi) = ([f64::MAX; 3], [f64::MIN; 3]);
    for p in &m.parts {
        let (offset, _) = p.placement();
        let extent = match p {
            Part::Box { half_extents, .. } => *half_extents,
            Part::Cylinder { radius, half_height, .. } => [*radius, *half_height, *radius],
            Part::ConvexHull { points, .. } => {
                for q in points {
                    for k in 0..3 {
                        lo[k] = lo[k].min(q[k] + offset[k]);
                        hi[k] = hi[k].max(q[k] + offset[k]);
                    }
                }
                continue;
            }
        };
        for k in 0..3 {
            lo[k] = lo[k].min(offset[k] - extent[k]);
            hi[k] = hi[k].max(offset[k] + extent[k]);
        }
    }
    let (cx, cz) = (0.5 * (lo[0] + hi[0]), 0.5 * (lo[2] + hi[2]));
    for p in &mut m.parts {
        let offset = match p {
            Part::Box { offset, .. } | Part::Cylinder { offset, .. } | Part::ConvexHull { offset, .. } => offset,
        };
        offset[0] -= cx;
        offset[2] -= cz;
    }
    m.size = [hi[0] - lo[0], hi[1].max(0.0), hi[2] - lo[2]];
    m
}

/// The whole catalogue, built once.
pub fn catalogue() -> &'static [Model] {
    static CATALOGUE: OnceLock<Vec<Model>> = OnceLock::new();
    CATALOGUE.get_or_init(|| build().into_iter().map(centred).collect())
}

/// The models of one kind, in catalogue order.
pub fn of_kind(kind: Kind) -> impl Iterator<Item = &'static Model> {
    catalogue().iter().filter(move |m| m.kind == kind)
}

/// The model named `name`.
pub fn by_name(name: &str) -> Option<&'static Model> {
    catalogue().iter().find(|m| m.name == name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn at_least_forty_models_with_unique_names_and_honest_sizes() {
        let all = catalogue();
        assert!(all.len() >= 40, "{} models", all.len());
        let mut names: Vec<_> = all.iter().map(|m| m.name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), all.len());
        for m in all {
            // The size is the parts' bounding box, centred on the origin, above the floor.
            let scene_shape = esrp_core::Shape::Parts(m.parts.clone());
            let _ = scene_shape;
            for p in &m.parts {
                let (offset, _) = p.placement();
                assert!(offset[0].abs() <= m.depth() / 2.0 + 1e-9, "{}: part outside depth", m.name);
                assert!(offset[2].abs() <= m.width() / 2.0 + 1e-9, "{}: part outside width", m.name);
                assert!(offset[1] >= 0.0, "{}: part below the floor", m.name);
            }
            assert!(m.depth() > 0.1 && m.width() > 0.1 && m.size[1] > 0.2, "{}: size {:?}", m.name, m.size);
            if m.movable.is_some() {
                assert!(m.depth().max(m.width()) <= 1.2 && m.size[1] <= 1.3, "{} is too big to carry", m.name);
            }
        }
        for category in MovableCategory::ALL {
            assert!(all.iter().filter(|m| m.movable == Some(category)).count() >= 3, "{category:?}");
        }
    }
}
